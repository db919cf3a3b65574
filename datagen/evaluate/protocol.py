"""What a planner is to `datagen evaluate`: the `Planner` protocol and its answer, a `Plan`.

Kept apart from the built-in planners (`datagen.evaluate.planners`) so that a planner module of its
own (the next-best-view players of `datagen.evaluate.sequential`, a plug-in) depends on the protocol
only, and the registry of every planner on them: no import runs both ways.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from datagen.evaluate.fixed import FixedPlans
from datagen.evaluate.situation import Situation
from schemas.config import GenerationConfig


@dataclass(frozen=True)
class Plan:
    """A planner's answer: the views to take after the initial one."""

    views: tuple[int, ...]
    ordered: bool = False
    """True: visit in this order; False: a one-shot set, ordered by the shortest open path."""
    probabilities: npt.NDArray[np.float64] | None = None
    at_count: Callable[[int], tuple[int, ...]] | None = field(default=None, compare=False)
    """The planner's answer had it been asked for exactly c new views (None: it only answers its own
    count): gives each run its coverage at every view count, and the views it needs to reach a share."""


class Planner(Protocol):
    name: str
    uses_refinement: bool
    """Whether the planner reads the refined input or the generator's label (the scene must be refined)."""

    def plan(self, situation: Situation) -> Plan: ...


def one_line(exc: BaseException, named: bool = True) -> str:
    """The first line of an exception's message, after its type's name unless ``named`` is False."""
    text = str(exc).strip()
    line = text.splitlines()[0] if text else ""
    return f"{type(exc).__name__}: {line}" if named or not line else line


@dataclass(frozen=True)
class PlannerContext:
    """What building a planner may need besides its spec: the evaluation's config (the oracle's label
    settings) and the fixed plans chosen from a training dataset (``--fixed-from``)."""

    config: GenerationConfig = field(default_factory=GenerationConfig)
    fixed: FixedPlans | None = None
    budget_views: int | None = None
    """``--budget-views``: how many views in all a next-best-view planner plays (default 10)."""


MATCH_PREFIX = "match="
"""``random:match=SPEC``: the argument that names the planner whose view count a random planner takes."""
