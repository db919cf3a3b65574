"""A trained checkpoint as a view scorer: what ``datagen evaluate --planner osvp:FILE`` loads.

The scorer takes what a dataset sample holds (the cloud's key centres in metres and the view state)
and returns one probability per view. The cloud is resampled to the checkpoint's point count by the
sample contract (`storage.samples.resample_cloud`) from a fixed stream, so a scene always gets the
same answer. It is a `schemas.planning.DecodingScorer`:
`CheckpointScorer.select_views` turns the probabilities into views with the checkpoint's default
decoding (``osvp:FILE``) or a named one (``osvp+size:FILE``, ``osvp+threshold=0.3:FILE``).
A checkpoint trained with a next-view target (``gain``, ``best_view``) is a next-best-view planner
instead (`NextViewCheckpointScorer`, a `schemas.planning.NextViewScorer`): asked after every view
with the cloud and the grid observed so far, it scores every view, and ``datagen evaluate`` visits
the best. A checkpoint of a grid network (``nbvnet``, ``scvp``) reads the occupancy grid the
evaluation builds (``uses_grid``) instead of the cloud.
`load_scorer` is the `schemas.planning.ScorerFactory` osvp registers as entry point ``osvp`` of the
group ``datagen.planners`` (pyproject.toml), through which ``datagen evaluate`` finds it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt
import torch

from osvp.checkpoint import Checkpoint, load_checkpoint
from osvp.decoding import DECODING_REGISTRY, parse_decoding, select_views
from osvp.loss import is_next_view
from schemas.planning import DecodingScorer, NextViewObservation, ScorerFactory
from storage.samples import resample_cloud

PLANNING_SEED = 0


class CheckpointScorer(DecodingScorer):
    """One probability per candidate view for a refined cloud and a view state."""

    def __init__(self, checkpoint: Checkpoint, device: str = "cpu") -> None:
        self.checkpoint = checkpoint
        self.device = device
        self.network = checkpoint.network(device)
        self.uses_grid = checkpoint.architecture.reads == "grid"
        """A grid network: ``datagen evaluate`` passes the input views' occupancy grid."""
        self.source = checkpoint.source
        """Which cloud the network was trained on: 'points' (refined) or 'observed' (sparse)."""
        self.tuned_threshold = checkpoint.tuned_threshold
        self.default_decoding = checkpoint.decoding
        self.decodings: tuple[str, ...] = tuple(
            name
            for name, rule in DECODING_REGISTRY.items()
            if not rule.needs_tuned_threshold or self.tuned_threshold is not None
        )
        """Decoding names this checkpoint accepts (``tuned`` only when it holds a tuned threshold)."""
        self.generation_config = checkpoint.generation_config
        """The generation config of the data it was trained on (None for older checkpoints): ``datagen
        evaluate`` images objects with it (`schemas.planning.ViewScorer`)."""

    def view_probabilities(
        self,
        points: npt.NDArray[np.float32],
        view_state: npt.NDArray[np.float32],
        grid: npt.NDArray[np.float32] | None = None,
    ) -> npt.NDArray[np.float64]:
        state = np.asarray(view_state, dtype=np.float32).reshape(-1)
        self.checkpoint.require(state.size, what="the planner's view space")
        if self.uses_grid:
            if grid is None:
                raise ValueError(f"{self.checkpoint.path}: a grid network needs the occupancy grid of its views")
            case = np.asarray(grid, dtype=np.float32)[None]
        else:
            cloud = np.asarray(points, dtype=np.float32).reshape(-1, 3)
            # the sample contract's resampling, from a stream of the scene's own (its point count)
            case = resample_cloud(cloud, self.checkpoint.num_points, (PLANNING_SEED, cloud.shape[0]))[None]
        with torch.no_grad():
            logits = self.network(torch.from_numpy(case).to(self.device), torch.from_numpy(state)[None].to(self.device))
        return torch.sigmoid(logits)[0].double().cpu().numpy()

    def select_views(
        self, probabilities: npt.NDArray[np.float64], view_state: npt.NDArray[np.float32], decoding: str | None = None
    ) -> npt.NDArray[np.bool_]:
        """One bool per view, True = take it (never a view of the view state); ``decoding`` None is the
        checkpoint's default. An unknown or malformed decoding is a one-line `ValueError`."""
        chosen = parse_decoding(decoding or self.default_decoding, self.tuned_threshold)
        p = np.asarray(probabilities, dtype=np.float64).reshape(-1)
        return select_views(p, np.asarray(view_state, dtype=np.float32).reshape(-1), chosen)


class NextViewCheckpointScorer:
    """A checkpoint of a next-view target as a next-best-view scorer: every view's predicted gain
    share (``gain``, PCNBV's manner) or class probability (``best_view``, NBVNet's; a sigmoid of its
    logit, which ranks the views as the softmax does) for what has been observed so far (the same
    network and resampling as `CheckpointScorer`)."""

    def __init__(self, checkpoint: Checkpoint, device: str = "cpu") -> None:
        self.predict = CheckpointScorer(checkpoint, device)
        self.uses_grid = self.predict.uses_grid
        self.generation_config = self.predict.generation_config

    def next_view_scores(self, observation: NextViewObservation) -> npt.NDArray[np.float64]:
        return self.predict.view_probabilities(observation.cloud, observation.view_state, observation.grid)


def load_scorer(path: str | Path, device: str = "cpu") -> CheckpointScorer | NextViewCheckpointScorer:
    """The scorer of an `osvp train` checkpoint (`CheckpointError` names what is wrong with the file):
    a one-shot `CheckpointScorer`, or a `NextViewCheckpointScorer` for a checkpoint of a next-view target."""
    checkpoint = load_checkpoint(path)
    if is_next_view(checkpoint.target):
        return NextViewCheckpointScorer(checkpoint, device)
    return CheckpointScorer(checkpoint, device)


_FACTORY: ScorerFactory = load_scorer
"""The entry point, typed: mypy holds `load_scorer` to the seam (`str` in, a scorer out)."""
