"""Training: one epoch learns, a resumed run equals an uninterrupted one, checkpoints are refused
with one clear message when they do not fit or are damaged."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from osvp.checkpoint import CheckpointError, load_checkpoint
from osvp.data import DataError, SampleBank, split_rows
from osvp.network import PRESETS, build_network
from osvp.train import TrainOptions, evaluate_rows, seeded_torch, stream_seed, train


@pytest.fixture(scope="module")
def bank(dataset_url: str) -> SampleBank:
    return SampleBank.load(dataset_url)


def options(dataset_url: str, out: Path, **changes: object) -> TrainOptions:
    base = {"data": dataset_url, "out": out, "epochs": 1, "batch_size": 16, "seed": 5}
    return TrainOptions(**{**base, **changes})  # type: ignore[arg-type]


def test_one_epoch_changes_the_weights_and_lowers_the_loss(bank: SampleBank, dataset_url: str, tmp_path: Path) -> None:
    opts = options(dataset_url, tmp_path / "run")
    train_rows, _ = split_rows(bank, opts.split, opts.val_fraction, opts.seed)
    with seeded_torch(stream_seed(opts.seed, 0, 0), "cpu"):
        initial = build_network(opts.preset, bank.num_views)  # exactly the network train() starts from
    before, _ = evaluate_rows(initial, bank, train_rows, PRESETS[opts.preset].num_points, opts)
    outcome = train(opts, bank=bank)
    trained = load_checkpoint(tmp_path / "run" / "last.pt").network()
    after, _ = evaluate_rows(trained, bank, train_rows, PRESETS[opts.preset].num_points, opts)
    changed = [k for k, v in initial.state_dict().items() if not torch.equal(v, trained.state_dict()[k])]
    assert len(changed) > 0.9 * len(initial.state_dict())
    assert after < before
    assert outcome.history[0]["train_loss"] > 0 and (tmp_path / "run" / "best.pt").is_file()
    csv_lines = (tmp_path / "run" / "metrics.csv").read_text().splitlines()
    assert csv_lines[0].startswith("epoch,train_loss,val_loss,precision,recall,f1") and len(csv_lines) == 2
    assert (tmp_path / "run" / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_resume_gives_the_weights_of_an_uninterrupted_run(bank: SampleBank, dataset_url: str, tmp_path: Path) -> None:
    straight = train(options(dataset_url, tmp_path / "straight", epochs=2), bank=bank)
    train(options(dataset_url, tmp_path / "resumed", epochs=1), bank=bank)
    resumed = train(options(dataset_url, tmp_path / "resumed", epochs=2, resume=True), bank=bank)
    a = load_checkpoint(tmp_path / "straight" / "last.pt")
    b = load_checkpoint(tmp_path / "resumed" / "last.pt")
    assert a.epoch == b.epoch == 2
    for key, value in a.data["model"].items():
        assert torch.equal(value, b.data["model"][key]), key
    timing = ("seconds", "train_samples_per_s", "loader_samples_per_s")
    runs = (straight, resumed)
    untimed = [[{k: v for k, v in row.items() if k not in timing} for row in run.history] for run in runs]
    assert untimed[0] == untimed[1]


def test_an_existing_run_is_not_overwritten_and_resume_needs_the_same_options(
    bank: SampleBank, dataset_url: str, tmp_path: Path
) -> None:
    train(options(dataset_url, tmp_path / "run"), bank=bank)
    with pytest.raises(DataError, match="--resume"):
        train(options(dataset_url, tmp_path / "run"), bank=bank)
    with pytest.raises(CheckpointError, match="other options"):
        train(options(dataset_url, tmp_path / "run", epochs=2, resume=True, lambda_=2.0), bank=bank)
    with pytest.raises(DataError, match="nothing to resume"):
        train(options(dataset_url, tmp_path / "fresh", resume=True), bank=bank)


def test_checkpoints_that_do_not_fit_or_are_damaged(bank: SampleBank, dataset_url: str, tmp_path: Path) -> None:
    train(options(dataset_url, tmp_path / "run"), bank=bank)
    checkpoint = load_checkpoint(tmp_path / "run" / "best.pt")
    with pytest.raises(CheckpointError, match="trained for 32 views but the dataset has 20"):
        checkpoint.require(20)
    with pytest.raises(CheckpointError, match="--points"):
        checkpoint.require(32, checkpoint.num_points + 1)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint at all" * 10)
    with pytest.raises(CheckpointError, match="not a readable osvp checkpoint"):
        load_checkpoint(garbage)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes((tmp_path / "run" / "best.pt").read_bytes()[:5000])
    with pytest.raises(CheckpointError):
        load_checkpoint(truncated)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(CheckpointError, match="no 'osvp-checkpoint' marker"):
        load_checkpoint(other)
    code = tmp_path / "code.pt"
    torch.save({"format": "osvp-checkpoint", "payload": np.random.default_rng(0)}, code)  # not plain data
    with pytest.raises(CheckpointError, match="not a readable osvp checkpoint"):
        load_checkpoint(code)
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "missing.pt")
