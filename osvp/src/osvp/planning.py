"""A trained checkpoint as a view scorer: what ``datagen evaluate --planner osvp:FILE`` loads.

The scorer takes what a dataset sample holds (the cloud's key centres in metres and the view state)
and returns one probability per view; ``datagen`` keeps those above 0.5. The cloud is resampled to
the checkpoint's point count from a fixed stream, so a scene always gets the same answer.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt
import torch

from osvp.checkpoint import Checkpoint, load_checkpoint

PLANNING_SEED = 0


class CheckpointScorer:
    """One probability per candidate view for a refined cloud and a view state."""

    def __init__(self, checkpoint: Checkpoint, device: str = "cpu") -> None:
        self.checkpoint = checkpoint
        self.device = device
        self.network = checkpoint.network(device)
        self.source = checkpoint.source
        """Which cloud the network was trained on: 'points' (refined) or 'observed' (sparse)."""

    def view_probabilities(
        self, points: npt.NDArray[np.float32], view_state: npt.NDArray[np.float32]
    ) -> npt.NDArray[np.float64]:
        state = np.asarray(view_state, dtype=np.float32).reshape(-1)
        self.checkpoint.require(state.size, what="the planner's view space")
        cloud = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        count, wanted = cloud.shape[0], self.checkpoint.num_points
        if count == 0:
            cloud = np.zeros((wanted, 3), dtype=np.float32)
        else:
            rng = np.random.default_rng(np.random.SeedSequence([PLANNING_SEED, count]))
            cloud = cloud[rng.choice(count, size=wanted, replace=count < wanted, shuffle=False)]
        with torch.no_grad():
            logits = self.network(
                torch.from_numpy(cloud)[None].to(self.device), torch.from_numpy(state)[None].to(self.device)
            )
        return torch.sigmoid(logits)[0].double().cpu().numpy()


def load_scorer(path: str | Path, device: str = "cpu") -> CheckpointScorer:
    """The scorer of an `osvp train` checkpoint (`CheckpointError` names what is wrong with the file)."""
    return CheckpointScorer(load_checkpoint(path), device)
