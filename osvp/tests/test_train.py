"""Training: one epoch learns, a resumed run equals an uninterrupted one with every target, the
checkpoint's tuned threshold and default decoding reach the planner, a version-1 dataset trains on
its labels only, and checkpoints are refused with one clear message when they do not fit or are
damaged."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from osvp.checkpoint import CheckpointError, load_checkpoint
from osvp.data import DataError, SampleBank, split_rows
from osvp.loss import ambiguity_targets, next_view_targets, targets
from osvp.metrics import tune_threshold
from osvp.network import PRESETS, build_network
from osvp.planning import load_scorer
from osvp.train import TrainOptions, predict_rows, run_rows, seeded_torch, stream_seed, train


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
    before, _ = predict_rows(initial, bank, train_rows, PRESETS[opts.preset].num_points, opts)
    outcome = train(opts, bank=bank)
    trained = load_checkpoint(tmp_path / "run" / "last.pt").network()
    after, _ = predict_rows(trained, bank, train_rows, PRESETS[opts.preset].num_points, opts)
    changed = [k for k, v in initial.state_dict().items() if not torch.equal(v, trained.state_dict()[k])]
    assert len(changed) > 0.9 * len(initial.state_dict())
    assert after < before
    assert outcome.history[0]["train_loss"] > 0 and (tmp_path / "run" / "best.pt").is_file()
    csv_lines = (tmp_path / "run" / "metrics.csv").read_text().splitlines()
    assert csv_lines[0].startswith("epoch,train_loss,val_loss,precision,recall,f1") and len(csv_lines) == 2
    assert (tmp_path / "run" / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("target", targets())
def test_resume_gives_the_weights_of_an_uninterrupted_run(
    target: str, bank: SampleBank, dataset_url: str, tmp_path: Path
) -> None:
    straight = train(options(dataset_url, tmp_path / "straight", epochs=2, target=target), bank=bank)
    train(options(dataset_url, tmp_path / "resumed", epochs=1, target=target), bank=bank)
    resumed = train(options(dataset_url, tmp_path / "resumed", epochs=2, resume=True, target=target), bank=bank)
    a = load_checkpoint(tmp_path / "straight" / "last.pt")
    b = load_checkpoint(tmp_path / "resumed" / "last.pt")
    assert a.epoch == b.epoch == 2 and a.target == b.target == target
    assert a.tuned_threshold == b.tuned_threshold == straight.history[-1]["tuned_threshold"]
    expected_metric = {"near_best": "chosen_gain_ratio"}.get(
        target, "best_view_accuracy" if target in next_view_targets() else "size_cover_f1"
    )
    assert straight.best_metric == expected_metric and all(row["train_loss"] > 0 for row in straight.history)
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
        train(options(dataset_url, tmp_path / "run", epochs=2, resume=True, lambda_=1.25), bank=bank)
    with pytest.raises(CheckpointError, match="other options"):
        train(options(dataset_url, tmp_path / "run", epochs=2, resume=True, target="support"), bank=bank)
    with pytest.raises(CheckpointError, match="other options"):
        train(options(dataset_url, tmp_path / "run", epochs=2, resume=True, max_objects=2), bank=bank)
    with pytest.raises(DataError, match="nothing to resume"):
        train(options(dataset_url, tmp_path / "fresh", resume=True), bank=bank)


def test_checkpoints_that_do_not_fit_or_are_damaged(bank: SampleBank, dataset_url: str, tmp_path: Path) -> None:
    train(options(dataset_url, tmp_path / "run"), bank=bank)
    checkpoint = load_checkpoint(tmp_path / "run" / "best.pt")
    with pytest.raises(CheckpointError, match="trained for 32 views but the dataset has 20"):
        checkpoint.require(20)
    with pytest.raises(CheckpointError, match="--points"):
        checkpoint.require(32, checkpoint.num_points + 1)
    unfit = load_checkpoint(tmp_path / "run" / "best.pt")
    unfit.data["model"].pop(next(iter(unfit.data["model"])))  # weights that no longer fit their network
    with pytest.raises(CheckpointError, match="its weights do not fit its own preset") as unfit_error:
        unfit.network()
    assert "\n" not in str(unfit_error.value)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint at all" * 10)
    with pytest.raises(CheckpointError, match="not a readable osvp checkpoint"):
        load_checkpoint(garbage)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes((tmp_path / "run" / "best.pt").read_bytes()[:5000])
    with pytest.raises(CheckpointError, match="not a readable osvp checkpoint") as truncated_error:
        load_checkpoint(truncated)
    line = str(truncated_error.value)
    assert "\n" not in line and line.endswith("); re-run `osvp train`")
    assert "If you are seeing this error" not in line  # torch's advice to its developers is cut off
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


def test_the_tuned_threshold_and_default_decoding_reach_the_planner(
    bank: SampleBank, dataset_url: str, tmp_path: Path
) -> None:
    opts = options(dataset_url, tmp_path / "run", target="marginal", split="objects", val_fraction=0.34)
    outcome = train(opts, bank=bank)
    checkpoint = load_checkpoint(tmp_path / "run" / "best.pt")
    assert checkpoint.version == 2 and checkpoint.target == "marginal" and checkpoint.decoding == "tuned"
    assert checkpoint.training["val_samples"] + checkpoint.training["train_samples"] == len(bank)
    # The stored threshold is the one tuned on the run's validation samples with these very weights.
    _, val_rows = run_rows(bank, opts)
    _, probabilities = predict_rows(checkpoint.network(), bank, val_rows, checkpoint.num_points, opts)
    covers = bank.covers.take(val_rows) if bank.covers is not None else None
    tuned, score = tune_threshold(probabilities, bank.view_state[val_rows], bank.labels[val_rows], covers)
    assert checkpoint.tuned_threshold == tuned and outcome.history[0]["tuned_f1"] == pytest.approx(score)
    scorer = load_scorer(tmp_path / "run" / "best.pt")
    assert scorer.decodings == ("threshold", "tuned", "size", "topk")
    p = np.linspace(0.0, 0.93, 32)  # view v scores 0.03 v; view 31 is already taken
    state = np.zeros(32, dtype=np.float32)
    state[31] = 1.0
    expected = [v for v in range(31) if p[v] > tuned]
    assert np.flatnonzero(scorer.select_views(p, state, None)).tolist() == expected
    assert np.flatnonzero(scorer.select_views(p, state, "tuned")).tolist() == expected
    assert np.flatnonzero(scorer.select_views(p, state, "threshold")).tolist() == list(range(17, 31))
    # size: free mass 0.03 * (0 + ... + 30) = 13.95 -> 14 views, the 14 best free ones
    assert np.flatnonzero(scorer.select_views(p, state, "size")).tolist() == list(range(17, 31))
    assert np.flatnonzero(scorer.select_views(p, state, "topk=2")).tolist() == [29, 30]
    with pytest.raises(ValueError, match="unknown decoding 'nope'; choose threshold, tuned, size, topk"):
        scorer.select_views(p, state, "nope")


def test_a_version_1_checkpoint_plans_with_the_papers_rule_and_is_not_resumed(
    bank: SampleBank, dataset_url: str, tmp_path: Path
) -> None:
    train(options(dataset_url, tmp_path / "run"), bank=bank)
    data = load_checkpoint(tmp_path / "run" / "last.pt").data
    old = {k: v for k, v in data.items() if k not in ("decoding", "tuned_threshold")} | {"version": 1}
    torch.save(old, tmp_path / "run" / "last.pt")
    checkpoint = load_checkpoint(tmp_path / "run" / "last.pt")
    assert (checkpoint.decoding, checkpoint.tuned_threshold) == ("threshold", None)
    scorer = load_scorer(tmp_path / "run" / "last.pt")
    assert scorer.decodings == ("threshold", "size", "topk")
    p = np.array([0.2, 0.7, 0.51, 0.9])
    assert scorer.select_views(p, np.array([0, 0, 0, 1], dtype=np.float32), None).tolist() == [0, 1, 1, 0]
    with pytest.raises(ValueError, match="no tuned threshold"):
        scorer.select_views(p, np.zeros(4, dtype=np.float32), "tuned")
    with pytest.raises(CheckpointError, match="older osvp"):
        train(options(dataset_url, tmp_path / "run", epochs=2, resume=True), bank=bank)


def test_a_version_1_dataset_trains_on_labels_and_refuses_the_other_targets(
    v1_dataset_url: str, tmp_path: Path
) -> None:
    old = SampleBank.load(v1_dataset_url)
    outcome = train(options(v1_dataset_url, tmp_path / "run", target="label"), bank=old)
    assert outcome.best_metric == "f1" and "cover_f1" not in outcome.history[0]
    assert 0.05 <= outcome.history[0]["tuned_threshold"] <= 0.95
    header = (tmp_path / "run" / "metrics.csv").read_text().splitlines()[0].split(",")
    assert "cover_f1" in header and "size_views" in header  # empty cells where there are no covers
    for target in ambiguity_targets():
        with pytest.raises(DataError, match=f"target '{target}' needs every sample's minimum covers") as info:
            train(options(v1_dataset_url, tmp_path / target, target=target), bank=old)
        assert "datagen shards relabel" in str(info.value) and not (tmp_path / target).exists()


def test_steps_give_every_training_set_the_same_optimisation(tmp_path: Path) -> None:
    """--steps 1000 at batch 32 is 32,000 sample passes: 4 epochs of 8,000 samples, 32 of 1,000; the learning
    rate halves once, after 80 % of the epochs."""
    options = TrainOptions(data="unused", out=tmp_path, steps=1000, batch_size=32)
    assert (options.for_samples(8000).epochs, options.for_samples(8000).lr_step) == (4, 4)
    assert (options.for_samples(1000).epochs, options.for_samples(1000).lr_step) == (32, 26)
    assert options.for_samples(10**6).epochs == 1
    plain = TrainOptions(data="unused", out=tmp_path, epochs=7)
    assert plain.for_samples(1000) is plain


@pytest.mark.parametrize("network", ["nbvnet", "scvp"])
def test_grid_networks_train_on_the_grid_and_resume_exactly(network: str, dataset_url: str, tmp_path: Path) -> None:
    """NBVNet-style (the best next view as a class) and SCVP-style (the nearest minimum cover) networks
    read each case's occupancy grid through the same loop, checkpoints and resume as osvp's."""
    grids = SampleBank.load(dataset_url, fields=("grid",))
    assert grids.samples.grids is not None and grids.batch([0, 1], 4, 0, 0).grid.shape == (2, 32, 32, 32)
    straight = train(options(dataset_url, tmp_path / "straight", epochs=2, network=network, fit_rows=20), bank=grids)
    train(options(dataset_url, tmp_path / "resumed", epochs=1, network=network, fit_rows=20), bank=grids)
    train(options(dataset_url, tmp_path / "resumed", epochs=2, network=network, resume=True, fit_rows=20), bank=grids)
    a, b = load_checkpoint(tmp_path / "straight" / "last.pt"), load_checkpoint(tmp_path / "resumed" / "last.pt")
    expected = {"nbvnet": ("best_view", "best_view_accuracy"), "scvp": ("mincover", "size_cover_f1")}[network]
    assert (a.architecture.name, a.target, straight.best_metric) == (network, *expected)
    assert a.num_points == 1 and a.preset.as_dict() == b.preset.as_dict()
    for key, value in a.data["model"].items():
        assert torch.equal(value, b.data["model"][key]), key
    row = straight.history[-1]
    assert (
        0.0 <= row[f"fit_{expected[1]}"] <= 1.0
        and f"fit_{expected[1]}" in (tmp_path / "straight" / "metrics.csv").read_text()
    )
    assert row[expected[1]] == a.training["history"][-1][expected[1]]


def test_a_grid_network_needs_a_version_3_dataset(v1_dataset_url: str, tmp_path: Path) -> None:
    with pytest.raises(DataError, match=r"network 'scvp' needs every case's next-view labels and occupancy grid"):
        train(options(v1_dataset_url, tmp_path / "run", network="scvp", target="label"))
    assert not (tmp_path / "run").exists()


def test_the_default_target_is_each_networks_best_measured_one(tmp_path: Path) -> None:
    """A plain run trains osvp on the nearest minimum cover at lambda 2 (the recipe's measured best), NBVNet on
    its class."""
    plain = TrainOptions(data="unused", out=tmp_path)
    assert (plain.target, plain.lambda_, plain.network) == ("mincover", 2.0, "osvp")
    assert TrainOptions(data="unused", out=tmp_path, network="nbvnet").target == "best_view"
    assert TrainOptions(data="unused", out=tmp_path, network="scvp", target="label").target == "label"


def test_init_starts_from_a_checkpoints_weights_and_refuses_another_network(
    bank: SampleBank, dataset_url: str, tmp_path: Path
) -> None:
    from osvp.train import _start, file_sha256

    train(options(dataset_url, tmp_path / "pre"), bank=bank)
    pre = load_checkpoint(tmp_path / "pre" / "last.pt")
    tuned = options(dataset_url, tmp_path / "tuned", init=tmp_path / "pre" / "last.pt", seed=9)
    network, *_ = _start(tuned, bank, tuned.num_points)
    for key, value in network.state_dict().items():
        assert torch.equal(value, pre.data["model"][key]), key
    train(tuned, bank=bank)
    recorded = load_checkpoint(tmp_path / "tuned" / "last.pt").training
    assert recorded["options"]["init"] == file_sha256(tmp_path / "pre" / "last.pt")
    assert recorded["options"] == tuned.identity()
    # The generation config of the training data travels with the weights, for `datagen evaluate`.
    assert load_checkpoint(tmp_path / "tuned" / "last.pt").data["generation_config"]["refiner"] == "none"
    grid = options(dataset_url, tmp_path / "grid", network="nbvnet", init=tmp_path / "pre" / "last.pt")
    with pytest.raises(CheckpointError, match=r"another size|same network"):
        train(grid, bank=bank)
    with pytest.raises(DataError, match="--init"):
        train(options(dataset_url, tmp_path / "both", init=tmp_path / "pre" / "last.pt", resume=True), bank=bank)


def test_val_data_validates_on_another_dataset_and_trains_on_all_of_data(
    bank: SampleBank, dataset_url: str, tmp_path: Path
) -> None:
    outcome = train(options(dataset_url, tmp_path / "run", val_data=dataset_url), bank=bank)
    record = load_checkpoint(tmp_path / "run" / "last.pt").training
    assert record["train_samples"] == record["val_samples"] == len(bank)
    assert record["options"]["val_data"] == dataset_url
    split = train(options(dataset_url, tmp_path / "split"), bank=bank)
    assert load_checkpoint(tmp_path / "split" / "last.pt").training["val_samples"] < len(bank)
    assert outcome.history[0]["val_loss"] != split.history[0]["val_loss"]


def test_case_balance_draws_every_case_size_alike_at_power_one() -> None:
    """--case-balance 1 gives the rare large cases as many draws as the common single-view ones; 0 is a
    permutation (every sample once); the same seed draws the same epoch."""
    from osvp.train import epoch_order

    sizes = np.repeat(np.array([1, 2, 3], dtype=np.int64), [900, 90, 10])
    rows = np.arange(1000, dtype=np.int64) + 5000
    plain = epoch_order(rows, sizes, np.random.default_rng(0), 0.0)
    assert sorted(plain.tolist()) == rows.tolist()
    balanced = epoch_order(rows, sizes, np.random.default_rng(0), 1.0)
    drawn = np.bincount(sizes[balanced - 5000], minlength=4)[1:]
    assert len(balanced) == 1000 and all(260 <= n <= 400 for n in drawn), drawn
    half = np.bincount(sizes[epoch_order(rows, sizes, np.random.default_rng(0), 0.5) - 5000], minlength=4)[1:]
    assert half[0] > half[1] > half[2] > 10, half  # between: rarer sizes gain, the order stays
    assert np.array_equal(balanced, epoch_order(rows, sizes, np.random.default_rng(0), 1.0))
