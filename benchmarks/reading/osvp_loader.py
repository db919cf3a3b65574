"""Benchmark: what feeds `osvp train` against the storage DataLoader path, on one dataset.

    python -m benchmarks.reading.osvp_loader --data URL [--points 2048] [--batch 32] [--seconds 10]

Measured in one run:

- baseline: `storage.torch.OSVPDataset` (``--points``), batch ``--batch``, 2 workers,
  `ShardShuffleSampler`: samples/s after the first batch (the reader path #14 measured);
- `osvp.data.SampleBank.load`: reading every sample once into memory (samples/s);
- `SampleBank.batch`: building shuffled batches of ``--points`` points from memory (samples/s);
- the small network's forward + backward on such batches (training samples/s on this machine).

and the ratio of each to the baseline. The loader keeps the model fed when the batch rate is far
above the training rate; the one-time read costs what the storage reader costs.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from osvp.data import SampleBank
from osvp.loss import sc_loss
from osvp.network import build_network

from storage.torch import OSVPDataset


def rate(count: int, seconds: float) -> float:
    return count / seconds if seconds > 0 else float("inf")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", required=True)
    parser.add_argument("--points", type=int, default=2048)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()

    dataset = OSVPDataset(args.data, num_points=args.points)
    loader = dataset.loader(args.batch, shuffle_seed=0, num_workers=2)
    seen, started = 0, None
    for batch in loader:
        if started is None:
            started = time.perf_counter()
            continue
        seen += len(batch)
        if time.perf_counter() - started > args.seconds:
            break
    baseline = rate(seen, time.perf_counter() - (started or time.perf_counter()))

    clock = time.perf_counter()
    bank = SampleBank.load(args.data)
    load_rate = rate(len(bank), time.perf_counter() - clock)

    order = np.random.default_rng(0).permutation(len(bank))
    clock, built = time.perf_counter(), 0
    while time.perf_counter() - clock < args.seconds and built < len(order):
        bank.batch(order[built : built + args.batch], args.points, seed=0, epoch=0)
        built += args.batch
    batch_rate = rate(built, time.perf_counter() - clock)

    network = build_network("small", bank.num_views)
    optimiser = torch.optim.AdamW(network.parameters(), lr=1e-3)
    clock, trained = time.perf_counter(), 0
    while time.perf_counter() - clock < args.seconds:
        batch = bank.batch(order[trained % len(order) :][: args.batch], 1024, seed=0, epoch=0)
        loss = sc_loss(network(batch.points, batch.view_state), batch.label)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        trained += int(batch.label.shape[0])
    train_rate = rate(trained, time.perf_counter() - clock)

    print(
        f"dataset {args.data}: {len(bank)} samples, {args.points} points, batch {args.batch}, torch threads "
        f"{torch.get_num_threads()}"
    )
    print("| path | samples/s | / baseline |\n|---|---|---|")
    for name, value in (
        ("storage DataLoader, 2 workers (baseline)", baseline),
        ("SampleBank.load (once per run)", load_rate),
        ("SampleBank.batch (every epoch)", batch_rate),
        ("small network forward + backward (1,024 points)", train_rate),
    ):
        print(f"| {name} | {value:,.0f} | {value / baseline:.2f} |")


if __name__ == "__main__":
    main()
