"""The data teaches something: a small PointNet that sees only the points (never view_state) predicts
held-out labels better than the best input-blind predictor, and loses that edge when clouds are
shuffled across samples.

Data: 12 cheap built-ins x 4 rotations (GenerationConfig(rotations=4), refiner none, every rotation of
every object; about 2,400 samples), read through OSVPDataset and a DataLoader with 2 workers, 512 points.

Hold-out: one rotation of every object (rotation = object's sorted position mod 4, so all four
rotations are held out for some objects), about 600 samples; training on the other three rotations.
Why not an object-level hold-out: measured with 9 training objects, it carries no usable signal. A
PointNet overfits and ends 8-12 % *above* the baseline BCE on 3 held-out objects (2 seeds), and even a
logistic regression on the true view_state only gets 3 % below it. Twelve shapes are too few to learn
geometry -> set cover across objects. Holding out rotations of seen objects asks the model to read from an
unseen cloud which object it is and which side was seen, and to map that to the views still needed.
That is the signal a dataset of this size can show.

Baseline: every view's label frequency on the training set, a constant per view (the minimum BCE of any
predictor that ignores its input). Measured locally with 800 steps (the seed below drives init and batch
order, through a torch.Generator):

    seed 0: model 9.6 % below the baseline BCE, shuffled clouds 0.0 %
    seed 1: 8.3 %, shuffled 0.0 %
    seed 2: 8.1 %, shuffled 0.0 %

so the assertion (>= 5 % relative) keeps about 3 points of room below the worst seed. The shuffled
control learns only the label marginals (its held-out BCE equals the baseline to 0.1 %).

Determinism: torch.manual_seed is a global seed shared with every other test; here init, batch order
and the shuffling permutation come from one local torch.Generator instead, resampling from
OSVPDataset's (seed, epoch, index) seeding, and torch runs on one thread.
"""

from __future__ import annotations

import math
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import pytest
import torch
from support.torch_data import Built, cached_dataset
from torch import nn
from torch.utils.data import DataLoader, Subset

from storage.torch import OSVPDataset

NUM_POINTS = 512
STEPS = 800
BATCH = 32
LEARNING_RATE = 3e-3
EPOCHS_LOADED = 3
"""Resamplings of the training clouds (set_epoch 0, 1, 2), cycled through during training."""
SEED = 0
MARGIN = 0.05
"""The model's held-out BCE must be at least 5 % below the baseline's."""

pytestmark = pytest.mark.slow


@pytest.fixture(scope="session")
def training(tmp_path_factory: pytest.TempPathFactory) -> Built:
    return cached_dataset("training", tmp_path_factory.mktemp("torch_training"))


class PointNet(nn.Module):
    """Shared MLP 3 -> 64 -> 128 on every point, max-pool, MLP 128 -> 128 -> 32 logits."""

    def __init__(self, generator: torch.Generator, prior: torch.Tensor) -> None:
        super().__init__()
        self.local = nn.Sequential(nn.Linear(3, 64), nn.ReLU(), nn.Linear(64, 128), nn.ReLU())
        self.head = nn.Sequential(nn.Linear(128, 128), nn.ReLU(), nn.Linear(128, 32))
        for module in self.modules():
            if isinstance(module, nn.Linear):  # nn.Linear's default init, from the local generator
                nn.init.kaiming_uniform_(module.weight, a=math.sqrt(5), generator=generator)
                bound = 1.0 / math.sqrt(module.weight.shape[1])
                nn.init.uniform_(module.bias, -bound, bound, generator=generator)
        with torch.no_grad():  # start from the baseline: logits of the training label frequencies
            self.head[-1].bias.copy_(torch.logit(prior))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        # raw world metres (objects of 0.05-0.15 m around the origin) scaled to about unit size
        return self.head(self.local(points * 10.0).max(dim=1).values)


def load(dataset: OSVPDataset, indices: list[int], epoch: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Clouds and labels of ``indices`` (in that order), read by 2 DataLoader workers."""
    dataset.set_epoch(epoch)
    position = {index: j for j, index in enumerate(indices)}
    points = torch.empty(len(indices), NUM_POINTS, 3)
    labels = torch.empty(len(indices), dataset.dataset.num_views)
    for batch in DataLoader(Subset(dataset, indices), batch_size=64, num_workers=2):
        rows = torch.tensor([position[i] for i in batch["index"].tolist()])
        points[rows] = batch["points"]
        labels[rows] = batch["label"]
    return points, labels


def train(
    data: list[tuple[torch.Tensor, torch.Tensor]], prior: torch.Tensor, seed: int, shuffle_clouds: bool
) -> PointNet:
    generator = torch.Generator().manual_seed(seed)
    model = PointNet(generator, prior)
    optimiser = torch.optim.Adam(model.parameters(), lr=LEARNING_RATE)
    count = data[0][1].shape[0]
    # the control: sample i is trained on sample cloud_of[i]'s cloud (one fixed permutation)
    cloud_of = torch.randperm(count, generator=generator) if shuffle_clouds else torch.arange(count)
    step = 0
    while step < STEPS:
        points, labels = data[(step * BATCH // count) % len(data)]
        order = torch.randperm(count, generator=generator)
        for start in range(0, count - BATCH + 1, BATCH):
            batch = order[start : start + BATCH]
            loss = nn.functional.binary_cross_entropy_with_logits(model(points[cloud_of[batch]]), labels[batch])
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            step += 1
            if step == STEPS:
                break
    return model.eval()


def test_pointnet_on_points_alone_beats_the_label_frequency_baseline(training: Built) -> None:
    started = time.perf_counter()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        dataset = OSVPDataset(training.url, num_points=NUM_POINTS, seed=SEED)
        index = dataset.dataset.index
        names = index.column("object_name").to_pylist()
        rotations = index.column("rotation").to_pylist()
        objects = sorted(set(names))
        assert len(objects) == 12 and sorted(set(rotations)) == [0, 1, 2, 3]
        held_out = [i for i, (n, r) in enumerate(zip(names, rotations, strict=True)) if r == objects.index(n) % 4]
        held = set(held_out)
        train_rows = [i for i in range(len(dataset)) if i not in held]
        assert 400 < len(held_out) < len(dataset) // 3

        data = [load(dataset, train_rows, epoch) for epoch in range(EPOCHS_LOADED)]
        test_points, test_labels = load(dataset, held_out, 0)
        # every resampling keeps the labels; the views' label frequencies are the baseline
        assert all(torch.equal(labels, data[0][1]) for _, labels in data)
        prior = data[0][1].mean(dim=0).clamp(1e-4, 1 - 1e-4)
        baseline = nn.functional.binary_cross_entropy(prior.expand_as(test_labels), test_labels).item()

        model = train(data, prior, SEED, shuffle_clouds=False)
        control = train(data, prior, SEED, shuffle_clouds=True)
        with torch.no_grad():
            model_bce = nn.functional.binary_cross_entropy_with_logits(model(test_points), test_labels).item()
            control_bce = nn.functional.binary_cross_entropy_with_logits(control(test_points), test_labels).item()
    finally:
        torch.set_num_threads(threads)
    gain, control_gain = 1 - model_bce / baseline, 1 - control_bce / baseline
    print(
        f"\nheld-out BCE: baseline {baseline:.4f}, model {model_bce:.4f} ({gain:+.1%}), "
        f"shuffled clouds {control_bce:.4f} ({control_gain:+.1%}); {time.perf_counter() - started:.0f} s"
    )
    assert gain >= MARGIN
    assert control_gain < MARGIN
    assert control_gain < gain - 0.03
    assert np.isfinite(model_bce)
