"""The view-state prior: the best SCLoss can do without looking at the cloud.

For every view state of the training samples, q_v is how often view v is in their labels. Knowing
only the view state, SCLoss is minimised by p_v = lambda q_v / (lambda q_v + 1 - q_v), which exceeds
one half exactly when lambda q_v > 1 - q_v. A view state never seen in training falls back to the
frequencies of all training samples with as many input views (or, failing that, of all of them).
A planner that does not beat this baseline has learned nothing from the points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float32]


@dataclass(frozen=True)
class ViewStatePrior:
    lambda_: float
    by_state: dict[bytes, FloatArray]
    """Label frequency per view, keyed by the view state's bytes."""
    by_size: dict[int, FloatArray]
    """Label frequency per view, keyed by the number of input views."""
    overall: FloatArray

    @classmethod
    def fit(cls, view_state: FloatArray, labels: FloatArray, lambda_: float) -> ViewStatePrior:
        """Frequencies from training rows (view_state and labels: (S, n) arrays of 0/1)."""
        if view_state.shape != labels.shape or view_state.shape[0] == 0:
            raise ValueError("the prior needs matching, non-empty (samples, views) arrays")
        states = view_state > 0.5
        keys, inverse = np.unique(np.packbits(states, axis=1), axis=0, return_inverse=True)
        by_state = {
            keys[i].tobytes(): labels[inverse.reshape(-1) == i].mean(axis=0).astype(np.float32)
            for i in range(len(keys))
        }
        sizes = states.sum(axis=1)
        by_size = {int(s): labels[sizes == s].mean(axis=0).astype(np.float32) for s in np.unique(sizes)}
        return cls(lambda_, by_state, by_size, labels.mean(axis=0).astype(np.float32))

    def frequencies(self, view_state: FloatArray) -> FloatArray:
        """q (S, n): each row's label frequencies, from the most specific group that has them."""
        states = view_state > 0.5
        packed = np.packbits(states, axis=1)
        rows = []
        for key, size in zip(packed, states.sum(axis=1).tolist(), strict=True):
            found = self.by_state.get(key.tobytes())
            rows.append(found if found is not None else self.by_size.get(int(size), self.overall))
        return np.stack(rows) if rows else np.zeros((0, self.overall.size), dtype=np.float32)

    def probabilities(self, view_state: FloatArray) -> FloatArray:
        """SCLoss's minimiser given the view state alone: lambda q / (lambda q + 1 - q)."""
        q = self.frequencies(view_state)
        weighted = self.lambda_ * q
        denominator = weighted + 1.0 - q
        return np.divide(weighted, denominator, out=np.zeros_like(q), where=denominator > 0).astype(np.float32)
