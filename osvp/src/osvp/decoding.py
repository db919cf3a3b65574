"""Decodings: how a network's per-view probabilities become a view set.

The paper keeps the views above 0.5 (``threshold``). A network trained on one arbitrary cover per
sample spreads its probability over interchangeable views, so that rule under-predicts (recall
0.36 with 3.5 views where the labels need 4.4); the other decodings correct for it:

- ``threshold`` (0.5) or ``threshold=T``: the views above T;
- ``tuned``: the views above the checkpoint's threshold, chosen on the run's validation samples
  (`osvp.metrics.tune_threshold`);
- ``size``: as many views as the probabilities add up to, the most probable first: k =
  round(sum p) over the views not yet taken (halves round up), at least 1 unless every such
  probability is below `TINY` (the network says nothing is missing);
- ``topk=K``: the K most probable views.

Views of the view state (already taken) are never selected; ties in probability go to the lower
view index. ``datagen evaluate`` reaches these as ``osvp+NAME:FILE`` through
`osvp.planning.CheckpointScorer.select_views`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from schemas.registry import Registry

PAPER_THRESHOLD = 0.5
TINY = 0.05
"""``size`` selects nothing when every free view's probability is below this."""


@dataclass(frozen=True)
class Decoding:
    """A parsed decoding: its name and its number (the threshold, or K for ``topk``)."""

    name: str
    value: float | None = None

    @property
    def spec(self) -> str:
        """The text that names it (``threshold=0.3``, ``tuned``, ``size``)."""
        return DECODING_REGISTRY[self.name].spec(self.name, self.value)


class DecodingRule(Protocol):
    """One decoding: the number its spec carries, how it is written, and the views it takes."""

    needs_tuned_threshold: bool
    """Whether it reads the checkpoint's tuned threshold (a checkpoint without one cannot take it)."""

    def spec(self, name: str, value: float | None) -> str:
        """The text that names the decoding with this number (``threshold=0.3``, ``topk=4``, ``size``)."""
        ...

    def value(self, text: str, argument: str | None, tuned_threshold: float | None) -> float | None:
        """The decoding's number (threshold, K) from its spec's ``=ARGUMENT`` (None: none was given)."""
        ...

    def take(
        self, p: npt.NDArray[np.float64], free: npt.NDArray[np.bool_], value: float | None
    ) -> npt.NDArray[np.bool_]:
        """(S, n) bools: the views taken, among the free ones, for (S, n) probabilities."""
        ...


DECODING_REGISTRY: Registry[DecodingRule] = Registry("decoding", "osvp.decodings", error=ValueError)
"""The decodings by name, in registration order (`register_decoding`); a package adds one as an entry
point of the group ``osvp.decodings`` naming an instance of its rule."""


def register_decoding(name: str) -> Callable[[type[DecodingRule]], type[DecodingRule]]:
    """Register a decoding: a new one is one decorated class with `value` and `take`."""

    def register(rule: type[DecodingRule]) -> type[DecodingRule]:
        DECODING_REGISTRY.register(name, rule())
        return rule

    return register


def _no_value(text: str, argument: str | None) -> None:
    if argument is not None:
        name = text.partition("=")[0]
        raise ValueError(f"decoding {text!r}: {name!r} takes no value; choose {', '.join(DECODING_REGISTRY.names())}")


class _Named:
    """A decoding written by its name alone."""

    needs_tuned_threshold = False

    def spec(self, name: str, value: float | None) -> str:
        return name


@register_decoding("threshold")
class _Threshold(_Named):
    def spec(self, name: str, value: float | None) -> str:
        return name if value in (None, PAPER_THRESHOLD) else f"{name}={value:g}"

    def value(self, text: str, argument: str | None, tuned_threshold: float | None) -> float | None:
        value = _number(argument, text) if argument is not None else PAPER_THRESHOLD
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"decoding {text!r}: the threshold must lie in [0, 1]")
        return value

    def take(
        self, p: npt.NDArray[np.float64], free: npt.NDArray[np.bool_], value: float | None
    ) -> npt.NDArray[np.bool_]:
        return (p > float(value if value is not None else PAPER_THRESHOLD)) & free


@register_decoding("tuned")
class _Tuned(_Threshold):
    needs_tuned_threshold = True

    def spec(self, name: str, value: float | None) -> str:
        return name

    def value(self, text: str, argument: str | None, tuned_threshold: float | None) -> float | None:
        _no_value(text, argument)
        if tuned_threshold is None:
            raise ValueError("decoding 'tuned': this checkpoint holds no tuned threshold (trained by an older osvp)")
        return float(tuned_threshold)


@register_decoding("size")
class _Size(_Named):
    def value(self, text: str, argument: str | None, tuned_threshold: float | None) -> float | None:
        _no_value(text, argument)
        return None

    def take(
        self, p: npt.NDArray[np.float64], free: npt.NDArray[np.bool_], value: float | None
    ) -> npt.NDArray[np.bool_]:
        counts = np.floor(np.where(free, p, 0.0).sum(axis=1) + 0.5).astype(np.int64)
        peak = np.where(free, p, -1.0).max(axis=1, initial=-1.0)
        return _most_probable(p, free, np.where(peak < TINY, 0, np.maximum(counts, 1)))


@register_decoding("topk")
class _TopK(_Named):
    def spec(self, name: str, value: float | None) -> str:
        return f"{name}={int(value or 0)}"

    def value(self, text: str, argument: str | None, tuned_threshold: float | None) -> float | None:
        if argument is None:
            raise ValueError("decoding 'topk' needs its K, e.g. topk=4")
        k = _number(argument, text)
        if k < 1 or k != int(k):
            raise ValueError(f"decoding {text!r}: K must be a whole number >= 1")
        return float(k)

    def take(
        self, p: npt.NDArray[np.float64], free: npt.NDArray[np.bool_], value: float | None
    ) -> npt.NDArray[np.bool_]:
        return _most_probable(p, free, np.full(p.shape[0], int(value or 0), dtype=np.int64))


def decodings() -> tuple[str, ...]:
    """The registered decodings' names (installed plug-ins included)."""
    return DECODING_REGISTRY.names()


def parse_decoding(text: str, tuned_threshold: float | None = None) -> Decoding:
    """``threshold``, ``threshold=T``, ``tuned``, ``size``, ``topk=K`` or another registered decoding;
    `ValueError` (one line, with the choices) for anything else, and for ``tuned`` when no tuned
    threshold is known."""
    name, equals, argument = text.partition("=")
    rule = DECODING_REGISTRY.get(name)
    if rule is None:
        raise ValueError(f"unknown decoding {text!r}; choose {', '.join(DECODING_REGISTRY.names())}")
    return Decoding(name, rule.value(text, argument if equals else None, tuned_threshold))


def _number(argument: str, text: str) -> float:
    try:
        value = float(argument)
    except ValueError:
        raise ValueError(f"decoding {text!r}: {argument!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"decoding {text!r}: {argument!r} is not a finite number")
    return value


def select_views(
    probabilities: npt.ArrayLike, view_state: npt.ArrayLike, decoding: Decoding | str
) -> npt.NDArray[np.bool_]:
    """The views ``decoding`` takes: (S, n) or (n,) bools for probabilities of that shape."""
    chosen = parse_decoding(decoding) if isinstance(decoding, str) else decoding
    p = np.asarray(probabilities, dtype=np.float64)
    state = np.asarray(view_state) > 0.5
    if p.shape != state.shape or p.ndim not in (1, 2):
        raise ValueError(f"probabilities {p.shape} and view state {state.shape} must be one (n,) or (S, n) shape")
    if p.ndim == 1:
        return select_views(p[None], state[None], chosen)[0]
    return DECODING_REGISTRY[chosen.name].take(p, ~state, chosen.value)


def _most_probable(
    p: npt.NDArray[np.float64], free: npt.NDArray[np.bool_], counts: npt.NDArray[np.int64]
) -> npt.NDArray[np.bool_]:
    """Per row, the ``counts`` most probable free views (ties to the lower index)."""
    order = np.argsort(np.where(free, -p, np.inf), axis=1, kind="stable")
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.arange(p.shape[1])[None, :].repeat(p.shape[0], axis=0), axis=1)
    return (rank < counts[:, None]) & free
