"""Training from a stream (`osvp.stream`, `osvp train --stream`): an epoch's streamed batches hold the
samples and tensors of the in-memory path, validation in memory on the validation rows alone judges
as the whole bank does, a streamed run resumed from last.pt equals an uninterrupted one, and a dataset
over ``--memory-limit`` streams by itself, saying so in one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from osvp.checkpoint import CheckpointError, load_checkpoint
from osvp.cli import main
from osvp.data import SampleBank
from osvp.network import PRESETS, build_network
from osvp.stream import StreamedRows, cap_rows, choose_streaming, index_bank, memory_estimate, rows_bank
from osvp.train import TrainOptions, predict_rows, run_rows, train

import storage

POINTS = 256
BATCH = 16


@pytest.fixture(scope="module")
def bank(dataset_url: str) -> SampleBank:
    return SampleBank.load(dataset_url)


def options(dataset_url: str, out: Path, **changes: object) -> TrainOptions:
    base = {"data": dataset_url, "out": out, "epochs": 1, "batch_size": BATCH, "seed": 5, "shuffle_buffer": 64}
    return TrainOptions(**{**base, **changes})  # type: ignore[arg-type]


def test_streamed_batches_are_the_in_memory_batches(bank: SampleBank, dataset_url: str) -> None:
    dataset = storage.open_dataset(dataset_url)
    opts = options(dataset_url, Path("unused"), split="objects", val_fraction=0.34)
    assert [r.tolist() for r in run_rows(index_bank(dataset), opts)] == [r.tolist() for r in run_rows(bank, opts)]
    train_rows, _ = run_rows(bank, opts)
    streamed = StreamedRows(dataset, train_rows, POINTS, BATCH, seed=5, covers=True, workers=2, shuffle_buffer=64)
    assert len(streamed) == train_rows.size
    for epoch in (0, 3):
        streamed.stream.set_epoch(epoch)
        order = [found.index for found in streamed.stream.loader()]
        assert sorted(torch.cat(order).tolist()) == train_rows.tolist(), "every training sample once"
        for rows, batch in zip(order, streamed.epoch(epoch), strict=True):
            expected = bank.batch(rows.numpy(), POINTS, seed=5, epoch=epoch, with_covers=True)
            for name in ("points", "view_state", "label", "index", "marginals", "support", "covers", "cover_mask"):
                assert torch.equal(getattr(batch, name), getattr(expected, name)), (epoch, name)


def test_validation_on_its_own_rows_judges_as_the_whole_bank(bank: SampleBank, dataset_url: str) -> None:
    dataset = storage.open_dataset(dataset_url)
    opts = options(dataset_url, Path("unused"))
    _, val_rows = run_rows(bank, opts)
    alone = rows_bank(dataset, val_rows)
    network = build_network(opts.preset, bank.num_views)
    num_points = PRESETS[opts.preset].num_points
    whole = predict_rows(network, bank, val_rows, num_points, opts)
    own = predict_rows(network, alone, np.arange(len(alone)), num_points, opts)
    assert whole[0] == own[0] and np.array_equal(whole[1], own[1])
    assert bank.covers is not None and alone.covers is not None
    assert np.array_equal(bank.covers.take(val_rows).covers, alone.covers.covers)
    capped = cap_rows(val_rows, 10, seed=5)
    assert capped.size == 10 and set(capped.tolist()) <= set(val_rows.tolist())
    assert np.array_equal(capped, cap_rows(val_rows, 10, seed=5)) and cap_rows(val_rows, 0, 5) is val_rows


def test_a_streamed_run_resumes_as_an_uninterrupted_one(bank: SampleBank, dataset_url: str, tmp_path: Path) -> None:
    straight = train(options(dataset_url, tmp_path / "straight", epochs=2, stream=True, target="mincover"))
    train(options(dataset_url, tmp_path / "resumed", epochs=1, stream=True, target="mincover"))
    resumed = train(options(dataset_url, tmp_path / "resumed", epochs=2, stream=True, target="mincover", resume=True))
    a, b = load_checkpoint(tmp_path / "straight" / "last.pt"), load_checkpoint(tmp_path / "resumed" / "last.pt")
    assert a.epoch == b.epoch == 2
    for key, value in a.data["model"].items():
        assert torch.equal(value, b.data["model"][key]), key
    timing = ("seconds", "train_samples_per_s", "loader_samples_per_s")
    untimed = [
        [{k: v for k, v in row.items() if k not in timing} for row in run.history] for run in (straight, resumed)
    ]
    assert untimed[0] == untimed[1] and all(row["train_loss"] > 0 for row in straight.history)
    train_rows, val_rows = run_rows(bank, options(dataset_url, tmp_path))
    assert a.training["train_samples"] == train_rows.size and a.training["val_samples"] == val_rows.size
    assert a.training["samples"] == len(bank) and a.training["options"]["stream"] is True
    with pytest.raises(CheckpointError, match="streaming as it did"):  # in memory it would train otherwise
        train(options(dataset_url, tmp_path / "resumed", epochs=3, target="mincover", resume=True), bank=bank)
    with pytest.raises(CheckpointError, match="other options"):
        train(
            options(dataset_url, tmp_path / "resumed", epochs=3, stream=True, target="mincover", resume=True, workers=1)
        )


def test_the_in_memory_mode_stays_the_default_and_records_what_it_did(dataset_url: str, tmp_path: Path) -> None:
    train(options(dataset_url, tmp_path / "run"))
    stored = load_checkpoint(tmp_path / "run" / "last.pt").training["options"]
    assert not {"stream", "workers", "shuffle_buffer", "val_cap", "memory_limit_gb"} & set(stored)
    capped = train(options(dataset_url, tmp_path / "capped", stream=True, val_cap=7))
    assert load_checkpoint(tmp_path / "capped" / "last.pt").training["val_samples"] == 7
    assert capped.history[0]["train_loss"] > 0


def test_over_the_memory_limit_it_streams_and_says_so(
    dataset_url: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dataset = storage.open_dataset(dataset_url)
    needed = memory_estimate(dataset)
    points = int(dataset.index.column("num_points").to_numpy().sum())
    assert 6 * points < needed < 6 * points + 2000 * len(dataset)
    assert choose_streaming(dataset_url, None, 8.0) == (False, "")
    assert choose_streaming(dataset_url, None, needed / 2e9)[0]
    args = ["train", "--data", dataset_url, "--out", str(tmp_path / "run"), "--epochs", "1", "--batch-size", "32"]
    assert main([*args, "--memory-limit", f"{needed / 2e9:.9f}", "--workers", "1"]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "stream" in line]
    assert len(lines) == 1 and "over --memory-limit" in lines[0] and "GB" in lines[0], lines
    stored = load_checkpoint(tmp_path / "run" / "last.pt").training["options"]
    assert stored["stream"] is True and stored["workers"] == 1
    assert main([*args[:4], str(tmp_path / "forced"), *args[5:], "--stream"]) == 0
    assert "streaming the training samples (--stream)" in capsys.readouterr().err
