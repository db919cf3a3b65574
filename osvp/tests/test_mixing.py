"""Mixing a second dataset into training (`osvp.mixing`): the epoch holds the asked share of mixed-in
samples, each mixed-in row once per pass, every own row once; a mixed batch is, sample by sample,
what each dataset gives alone (covers padded); the run records the mix, steps count it, a resume
with another mix is refused, and a dataset that does not match is one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from osvp.checkpoint import CheckpointError, load_checkpoint
from osvp.cli import main
from osvp.data import DataError, SampleBank
from osvp.mixing import MIX_STREAM, Mixture, epoch_plan, mixed_count, mixed_seed
from osvp.train import TrainOptions, _bank_batches, run_rows, train


@pytest.fixture(scope="module")
def bank(dataset_url: str) -> SampleBank:
    return SampleBank.load(dataset_url)


@pytest.fixture(scope="module")
def mixed_in(dataset_url: str) -> SampleBank:
    """The same dataset read again: its samples come through the mixed-in path, with their own streams."""
    return SampleBank.load(dataset_url)


def options(dataset_url: str, out: Path, **changes: object) -> TrainOptions:
    """One epoch of batches of 16 at seed 5 unless changed."""
    return TrainOptions(data=dataset_url, out=out, **({"epochs": 1, "batch_size": 16, "seed": 5} | changes))  # type: ignore[arg-type]


def test_an_epoch_holds_the_asked_share_and_every_mixed_row_once_per_pass() -> None:
    own = np.arange(300, dtype=np.int64)[::-1].copy()
    for fraction, mixed_rows in ((0.25, 1000), (0.5, 120), (0.9, 700)):
        is_mixed, drawn = epoch_plan(own, mixed_rows, fraction, np.random.default_rng(3))
        wanted = mixed_count(len(own), fraction)
        assert int(is_mixed.sum()) == len(drawn) == wanted and len(is_mixed) == len(own) + wanted
        assert abs(wanted / len(is_mixed) - fraction) < 1e-2
        counts = np.bincount(drawn, minlength=mixed_rows)
        assert counts.max() - counts.min() <= 1  # every row once before any row twice
        again = epoch_plan(own, mixed_rows, fraction, np.random.default_rng(3))
        assert np.array_equal(again[0], is_mixed) and np.array_equal(again[1], drawn)
    assert mixed_count(300, 0.25) == 100
    for bad in (0.0, 1.0, -0.1):
        with pytest.raises(DataError, match="--mix-fraction"):
            mixed_count(300, bad)


def test_a_mixed_batch_is_what_each_dataset_gives_alone(
    bank: SampleBank, mixed_in: SampleBank, dataset_url: str, tmp_path: Path
) -> None:
    """Rebuilt one sample at a time from the plan: own rows from the run's stream, mixed-in rows from
    theirs, and the listed covers padded with empty, masked-out covers."""
    opts = options(dataset_url, tmp_path, target="mincover", mix_data=dataset_url, mix_fraction=0.4)
    rows, _ = run_rows(bank, opts)
    mixture = Mixture(mixed_in, 0.4)
    epoch = 1
    batches = list(_bank_batches(bank, rows, opts, epoch, mixture))
    own_order = np.random.default_rng(np.random.SeedSequence([opts.seed, epoch, 1])).permutation(rows)
    is_mixed, drawn = epoch_plan(
        own_order, len(mixed_in), 0.4, np.random.default_rng(np.random.SeedSequence([opts.seed, epoch, MIX_STREAM]))
    )
    assert sum(len(b) for b in batches) == len(is_mixed) == len(rows) + mixture.count(len(rows))
    own_at = mixed_at = 0
    position = 0
    for batch in batches:
        assert batch.covers is not None and batch.cover_mask is not None
        for i in range(len(batch)):
            if is_mixed[position]:
                alone = mixed_in.batch([drawn[mixed_at]], opts.num_points, mixed_seed(opts.seed), epoch, True)
                mixed_at += 1
            else:
                alone = bank.batch([own_order[own_at]], opts.num_points, opts.seed, epoch, True)
                own_at += 1
            position += 1
            assert torch.equal(batch.points[i], alone.points[0]) and torch.equal(batch.label[i], alone.label[0])
            assert torch.equal(batch.view_state[i], alone.view_state[0])
            assert alone.covers is not None and alone.cover_mask is not None
            listed = int(alone.covers.shape[1])
            assert torch.equal(batch.covers[i, :listed], alone.covers[0])
            assert torch.equal(batch.cover_mask[i, :listed], alone.cover_mask[0])
            assert not batch.cover_mask[i, listed:].any() and not batch.covers[i, listed:].any()
    assert any(is_mixed) and not all(is_mixed)


def test_the_run_records_the_mix_counts_it_in_steps_and_resumes_only_alike(
    bank: SampleBank, dataset_url: str, tmp_path: Path
) -> None:
    own_rows = len(run_rows(bank, options(dataset_url, tmp_path))[0])
    steps = -(-3 * own_rows // (2 * 16))  # one and a half epochs of the own rows alone
    mixed = options(dataset_url, tmp_path / "mixed", steps=steps, mix_data=dataset_url, mix_fraction=0.5)
    plain = options(dataset_url, tmp_path / "plain", steps=steps)
    train(mixed, bank=bank)
    train(plain, bank=bank)
    a, b = (load_checkpoint(tmp_path / name / "last.pt") for name in ("mixed", "plain"))
    assert a.training["options"]["mix_data"] == dataset_url and a.training["options"]["mix_fraction"] == 0.5
    assert "mix_data" not in b.training["options"] and "mix_fraction" not in b.training["options"]
    assert a.training["train_samples"] == b.training["train_samples"] == own_rows
    assert (a.epoch, b.epoch) == (1, 2)  # an epoch of twice the samples: half the epochs for the same steps
    resumed = options(dataset_url, tmp_path / "mixed", epochs=a.epoch + 1, resume=True)
    with pytest.raises(CheckpointError, match="--mix-data"):
        train(resumed, bank=bank)


def test_a_mismatched_or_misused_mix_is_one_line(
    dataset_url: str, v1_dataset_url: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["train", "--data", dataset_url, "--out", str(tmp_path / "run"), "--epochs", "1", "--target", "label"]
    asked = (
        (["--mix-data", v1_dataset_url, "--mix-fraction", "0.3"], "schema version"),
        (["--mix-fraction", "0.3"], "needs --mix-data"),
        (["--mix-data", dataset_url, "--mix-fraction", "1.5"], "in (0, 1)"),
        (["--mix-data", dataset_url, "--mix-fraction", "0.3", "--stream"], "without --stream"),
    )
    for extra, reason in asked:
        assert main([*args, *extra]) == 2
        err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("read ")]
        assert len(err) == 1 and err[0].startswith("error: ") and reason in err[0], err
    assert not (tmp_path / "run" / "last.pt").exists()
