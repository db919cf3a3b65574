"""SCLoss, the paper's set-covering loss (AIR-OSVP equation 3), and targets that allow for ties.

Per view, the binary cross entropy of the predicted probability against the label bit; the
label's 1s weigh ``lambda_`` times its 0s (views that must be taken matter more than views that
need not), averaged over views and over the batch. The paper picks lambda = 1.25 for the best F1.
Computed from logits (softplus / ``binary_cross_entropy_with_logits``), which is the same value
without the overflow of log(sigmoid) near 0 and 1. The authors' code sums instead of averaging;
the scale only changes the effective learning rate.

The ``gain`` target trains the same network as a next-best-view planner in the manner of PCNBV:
every view's share of new surface (a version-3 dataset's ``view_gain``) regressed by the sigmoid of
its logit, mean squared error (PCNBV sums it; the scale only changes the effective learning rate).
The ``best_view`` target is NBVNet's: the best next view as a class, cross entropy.

A stored label is one arbitrary minimum cover among many equally good ones (median 9), so SCLoss
on it punishes a network for predicting another, equally good cover. The other targets
(`TARGETS`, chosen with ``osvp train --target``) use what a version-2 dataset keeps about the
ties: the per-view marginals over the minimum covers, the covers themselves, or their support.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch
import torch.nn.functional as F

from schemas.errors import DatagenError
from schemas.registry import Registry
from storage.samples import SAMPLE_FIELDS

DEFAULT_LAMBDA = 1.25


def _check(logits: torch.Tensor, targets: torch.Tensor, lambda_: float) -> None:
    if logits.shape != targets.shape:
        raise ValueError(f"logits {tuple(logits.shape)} and labels {tuple(targets.shape)} must have one shape")
    if lambda_ <= 0:
        raise ValueError(f"lambda = {lambda_} must be positive")


def sc_loss(logits: torch.Tensor, labels: torch.Tensor, lambda_: float = DEFAULT_LAMBDA) -> torch.Tensor:
    """Target ``label``: mean over the batch of SCLoss = -(1/|V|) sum_i [(1 - g_i) CE_i + lambda g_i CE_i].

    Rewards predicting exactly the stored label, the lexicographically smallest minimum cover."""
    _check(logits, labels, lambda_)
    labels = labels.to(logits.dtype)
    per_view = F.binary_cross_entropy_with_logits(logits, labels, reduction="none")
    weights = 1.0 + (lambda_ - 1.0) * labels
    return (weights * per_view).mean()


def marginal_loss(logits: torch.Tensor, marginals: torch.Tensor, lambda_: float = DEFAULT_LAMBDA) -> torch.Tensor:
    """Target ``marginal``: SCLoss with soft targets q, lambda q (-log p) + (1 - q)(-log(1 - p)),
    averaged over views and samples.

    Rewards each view's probability following how often it is in a minimum cover: a view every
    cover needs is pushed to 1, one no cover uses to 0, and an interchangeable view sits between,
    so no single tie-break is learnt. With 0/1 marginals it is SCLoss."""
    _check(logits, marginals, lambda_)
    q = marginals.to(logits.dtype)
    return (lambda_ * q * F.softplus(-logits) + (1.0 - q) * F.softplus(logits)).mean()


def mincover_loss(
    logits: torch.Tensor, covers: torch.Tensor, cover_mask: torch.Tensor, lambda_: float = DEFAULT_LAMBDA
) -> torch.Tensor:
    """Target ``mincover``: per sample the least SCLoss over its listed minimum covers (``covers``
    (B, C, n) 0/1, ``cover_mask`` (B, C) True for real ones), averaged over the batch.

    Set-prediction matching: rewards predicting any one minimum cover, whichever the network finds
    easiest; only the cover it is closest to receives gradient."""
    if covers.dim() != 3 or covers.shape[0] != logits.shape[0] or covers.shape[2] != logits.shape[1]:
        shapes = f"covers {tuple(covers.shape)}, logits {tuple(logits.shape)}"
        raise ValueError(f"{shapes}: covers must be (batch, covers, views) for (batch, views) logits")
    if cover_mask.shape != covers.shape[:2] or not bool(cover_mask.any(dim=1).all()):
        raise ValueError("cover_mask must be (batch, covers) with at least one cover per sample")
    if lambda_ <= 0:
        raise ValueError(f"lambda = {lambda_} must be positive")
    g = covers.to(logits.dtype)
    chosen, skipped = F.softplus(-logits), F.softplus(logits)  # -log p, -log(1 - p)
    # sum_v [lambda g_v (-log p_v) + (1 - g_v)(-log(1 - p_v))] = sum_v skipped_v + g . (lambda chosen - skipped)
    per_cover = (skipped.sum(dim=1, keepdim=True) + torch.einsum("bcn,bn->bc", g, lambda_ * chosen - skipped)) / (
        logits.shape[1]
    )
    per_cover = per_cover.masked_fill(~cover_mask.to(torch.bool), float("inf"))
    return per_cover.min(dim=1).values.mean()


def support_loss(
    logits: torch.Tensor, labels: torch.Tensor, support: torch.Tensor, lambda_: float = DEFAULT_LAMBDA
) -> torch.Tensor:
    """Target ``support``: SCLoss on the stored label, with weight 0 on the views of other minimum
    covers (support minus label), still averaged over all views.

    Rewards the label's views and punishes views no minimum cover uses, but never a view that
    would belong to an equally good cover."""
    _check(logits, labels, lambda_)
    _check(logits, support, lambda_)
    labels = labels.to(logits.dtype)
    per_view = F.binary_cross_entropy_with_logits(logits, labels, reduction="none")
    excused = (support > 0.5) & (labels < 0.5)
    weights = (1.0 + (lambda_ - 1.0) * labels).masked_fill(excused, 0.0)
    return (weights * per_view).mean()


def gain_loss(logits: torch.Tensor, gains: torch.Tensor) -> torch.Tensor:
    """Target ``gain``: mean over views and samples of (sigmoid(logit) - gain share)^2."""
    if logits.shape != gains.shape:
        raise ValueError(f"logits {tuple(logits.shape)} and gains {tuple(gains.shape)} must have one shape")
    return F.mse_loss(torch.sigmoid(logits), gains.to(logits.dtype))


def best_view_loss(logits: torch.Tensor, view_state: torch.Tensor, best_view: torch.Tensor) -> torch.Tensor:
    """Target ``best_view``: cross entropy of the best next view as a class among the open views
    (NBVNet's classification; the views taken are masked out, as play never visits them), averaged
    over the samples that have a next view (``best_view`` >= 0). 0 for a batch with none."""
    if view_state.shape != logits.shape or best_view.shape != logits.shape[:1]:
        shapes = f"logits {tuple(logits.shape)}, view state {tuple(view_state.shape)}"
        raise ValueError(f"{shapes}, best view {tuple(best_view.shape)}: need (batch, views) twice and (batch,)")
    has_next = best_view >= 0
    if not bool(has_next.any()):
        return logits.sum() * 0.0
    masked = logits.masked_fill(view_state > 0.5, torch.finfo(logits.dtype).min)
    return F.cross_entropy(masked[has_next], best_view[has_next].long())


NEAR_BEST_TEMPERATURE = 0.1
"""`near_best_loss`'s temperature, as a share of the sample's best gain: a view with 90 % of the best
gain weighs e^-1 of the best view, one with half of it e^-5."""


def near_best_loss(
    logits: torch.Tensor, view_state: torch.Tensor, gains: torch.Tensor, temperature: float = NEAR_BEST_TEMPERATURE
) -> torch.Tensor:
    """Target ``near_best``: cross entropy over the open views against soft classes, each open view
    weighted by exp((gain - best gain) / (temperature x best gain)), averaged over the samples with
    something left to see (best gain > 0).

    NBVNet's class with credit for views that see nearly as much: play is judged on what the views
    see, not on naming the one best view, and equal or nearly equal gains (a symmetric object, a view
    pair on either side of it) no longer pull the network towards an arbitrary index."""
    if view_state.shape != logits.shape or gains.shape != logits.shape:
        shapes = f"logits {tuple(logits.shape)}, view state {tuple(view_state.shape)}, gains {tuple(gains.shape)}"
        raise ValueError(f"{shapes}: need (batch, views) three times")
    taken = view_state > 0.5
    gains = gains.to(logits.dtype).masked_fill(taken, 0.0)
    best = gains.max(dim=1).values
    has_next = best > 0
    if not bool(has_next.any()):
        return logits.sum() * 0.0
    scaled = (gains[has_next] - best[has_next, None]) / (temperature * best[has_next, None])
    soft = torch.softmax(scaled.masked_fill(taken[has_next], -torch.inf), dim=1)
    masked = logits[has_next].masked_fill(taken[has_next], torch.finfo(logits.dtype).min)
    return -(soft * F.log_softmax(masked, dim=1)).sum(dim=1).mean()


class TargetBatch(Protocol):
    """What a target reads from a batch (`osvp.data.Batch`)."""

    @property
    def label(self) -> torch.Tensor: ...
    @property
    def marginals(self) -> torch.Tensor | None: ...
    @property
    def support(self) -> torch.Tensor | None: ...
    @property
    def covers(self) -> torch.Tensor | None: ...
    @property
    def cover_mask(self) -> torch.Tensor | None: ...
    @property
    def view_gain(self) -> torch.Tensor | None: ...
    @property
    def view_state(self) -> torch.Tensor: ...
    @property
    def best_view(self) -> torch.Tensor | None: ...


TargetLoss = Callable[[torch.Tensor, TargetBatch, float], torch.Tensor]
"""(logits, batch, lambda) -> the loss, on the logits' device."""


@dataclass(frozen=True)
class Target:
    """A training target: its loss and the batch fields it reads (`storage.sample_fields` names, which
    decide the dataset version it needs and whether it needs the minimum covers)."""

    name: str
    loss: TargetLoss
    reads: tuple[str, ...]
    """The `osvp.data.Batch` fields the loss reads; each a registered sample field."""
    selected_by: str | None = None
    """The validation figure ``best.pt`` maximises, when not the kind's default (`osvp.train.selection_metric`)."""
    figures: tuple[str, ...] = ()
    """Validation figures it adds beside its kind's (``gain_mae`` for a gain regression)."""

    @property
    def needs_ties(self) -> bool:
        """Whether it reads what a dataset keeps about the minimum covers (schema version 2 on)."""
        return any(SAMPLE_FIELDS[name].covers for name in self.reads)

    @property
    def reads_covers(self) -> bool:
        """Whether its batches carry the listed covers (padded per batch)."""
        return "covers" in self.reads

    @property
    def since(self) -> int:
        """The first schema version whose datasets hold every field it reads."""
        return max([1, *(SAMPLE_FIELDS[name].since for name in self.reads)])

    @property
    def next_view(self) -> bool:
        """Whether it trains a next-best-view planner: it reads the next-view labels (version 3)."""
        return self.since >= 3


class UnknownTarget(DatagenError, ValueError):
    """A training target no `Target` is registered for."""


TARGET_REGISTRY: Registry[Target] = Registry(
    "training target", "osvp.targets", error=UnknownTarget, check=lambda entry: isinstance(entry, Target)
)
"""The targets `osvp train --target` can name, in registration order (`register_target`); a package
adds one as an entry point of the group ``osvp.targets`` naming its `Target`."""


def register_target(
    name: str, reads: tuple[str, ...], selected_by: str | None = None, figures: tuple[str, ...] = ()
) -> Callable[[TargetLoss], TargetLoss]:
    """Register a target: a new one is one decorated function of (logits, batch, lambda) and the
    batch fields it reads."""
    unknown = [field for field in reads if field not in SAMPLE_FIELDS]
    if unknown:
        raise ValueError(f"target {name!r} reads {', '.join(unknown)}, which no sample field is")

    def register(loss: TargetLoss) -> TargetLoss:
        TARGET_REGISTRY.register(name, Target(name, loss, reads, selected_by, figures))
        return loss

    return register


def _need(target: str, value: torch.Tensor | None, what: str, logits: torch.Tensor) -> torch.Tensor:
    if value is None:
        raise ValueError(f"target {target!r} needs the batch's {what} (a version-2 dataset)")
    return value.to(logits.device)


@register_target("label", reads=("label",))
def _label(logits: torch.Tensor, batch: TargetBatch, lambda_: float) -> torch.Tensor:
    return sc_loss(logits, batch.label.to(logits.device), lambda_)


@register_target("marginal", reads=("marginals",))
def _marginal(logits: torch.Tensor, batch: TargetBatch, lambda_: float) -> torch.Tensor:
    return marginal_loss(logits, _need("marginal", batch.marginals, "marginals", logits), lambda_)


@register_target("mincover", reads=("covers", "cover_mask"))
def _mincover(logits: torch.Tensor, batch: TargetBatch, lambda_: float) -> torch.Tensor:
    covers = _need("mincover", batch.covers, "covers", logits)
    return mincover_loss(logits, covers, _need("mincover", batch.cover_mask, "cover mask", logits), lambda_)


@register_target("support", reads=("label", "support"))
def _support(logits: torch.Tensor, batch: TargetBatch, lambda_: float) -> torch.Tensor:
    labels = batch.label.to(logits.device)
    return support_loss(logits, labels, _need("support", batch.support, "support", logits), lambda_)


@register_target("gain", reads=("view_gain",), figures=("gain_mae",))
def _gain(logits: torch.Tensor, batch: TargetBatch, lambda_: float) -> torch.Tensor:
    if batch.view_gain is None:
        raise ValueError("target 'gain' needs every view's gain (a version-3 dataset)")
    return gain_loss(logits, batch.view_gain.to(logits.device))


@register_target("best_view", reads=("view_state", "best_view"))
def _best_view(logits: torch.Tensor, batch: TargetBatch, lambda_: float) -> torch.Tensor:
    if batch.best_view is None:
        raise ValueError("target 'best_view' needs every sample's best next view (a version-3 dataset)")
    return best_view_loss(logits, batch.view_state.to(logits.device), batch.best_view.to(logits.device))


@register_target("near_best", reads=("view_state", "view_gain"), selected_by="chosen_gain_ratio")
def _near_best(logits: torch.Tensor, batch: TargetBatch, lambda_: float) -> torch.Tensor:
    if batch.view_gain is None:
        raise ValueError("target 'near_best' needs every view's gain (a version-3 dataset)")
    return near_best_loss(logits, batch.view_state.to(logits.device), batch.view_gain.to(logits.device))


def targets() -> tuple[str, ...]:
    """The registered targets' names (installed plug-ins included)."""
    return TARGET_REGISTRY.names()


def ambiguity_targets() -> tuple[str, ...]:
    """Targets that need every sample's minimum covers (schema version 2)."""
    return tuple(name for name, target in TARGET_REGISTRY.items() if target.needs_ties)


def next_view_targets() -> tuple[str, ...]:
    """Targets that train a next-best-view planner on every view's gain (schema version 3)."""
    return tuple(name for name, target in TARGET_REGISTRY.items() if target.next_view)


def is_next_view(target: str) -> bool:
    """Whether ``target`` (a registered name) trains a next-best-view planner."""
    found = TARGET_REGISTRY.get(target)
    return found is not None and found.next_view


def target_loss(target: str, logits: torch.Tensor, batch: TargetBatch, lambda_: float) -> torch.Tensor:
    """The loss of the registered ``target`` on a batch, on the logits' device."""
    return TARGET_REGISTRY[target].loss(logits, batch, lambda_)
