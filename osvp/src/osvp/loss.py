"""SCLoss, the paper's set-covering loss (AIR-OSVP equation 3).

Per view, the binary cross entropy of the predicted probability against the label bit; the
label's 1s weigh ``lambda_`` times its 0s (views that must be taken matter more than views that
need not), averaged over views and over the batch. The paper picks lambda = 1.25 for the best F1.
Computed from logits (``binary_cross_entropy_with_logits``), which is the same value without the
overflow of log(sigmoid) near 0 and 1. The authors' code sums instead of averaging; the scale only
changes the effective learning rate.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

DEFAULT_LAMBDA = 1.25


def sc_loss(logits: torch.Tensor, labels: torch.Tensor, lambda_: float = DEFAULT_LAMBDA) -> torch.Tensor:
    """Mean over the batch of SCLoss = -(1/|V|) sum_i [(1 - g_i) CE_i + lambda g_i CE_i]."""
    if logits.shape != labels.shape:
        raise ValueError(f"logits {tuple(logits.shape)} and labels {tuple(labels.shape)} must have one shape")
    if lambda_ <= 0:
        raise ValueError(f"lambda = {lambda_} must be positive")
    labels = labels.to(logits.dtype)
    per_view = F.binary_cross_entropy_with_logits(logits, labels, reduction="none")
    weights = 1.0 + (lambda_ - 1.0) * labels
    return (weights * per_view).mean()
