"""`osvp train | eval | sweep-lambda` end to end on the small dataset; user errors are one line, exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from osvp.cli import main
from osvp.train import TrainOptions, train


def test_train_then_eval(dataset_url: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    args = ["train", "--data", dataset_url, "--out", str(out), "--epochs", "2", "--batch-size", "32"]
    assert main([*args, "--target", "support", "--split", "objects", "--val-fraction", "0.34"]) == 0
    err = capsys.readouterr().err
    assert "epoch 2/2" in err and "best validation F1 (against the nearest minimum cover, size decoding)" in err
    assert "cover F1" in err and "size:" in err and "tuned" in err
    assert sorted(p.name for p in out.iterdir()) == ["best.pt", "curves.png", "last.pt", "metrics.csv"]
    assert main(["eval", "--data", dataset_url, "--checkpoint", str(out / "best.pt"), "--split", "val", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert set(report) == {
        "samples",
        "loss",
        "target",
        "default_decoding",
        "tuned_threshold",
        "decodings",
        "view_state_prior",
    }
    assert report["target"] == "support" and report["default_decoding"] == "tuned"
    assert list(report["decodings"]) == ["threshold", "tuned", "size"]
    assert list(report["view_state_prior"]) == ["threshold", "size"]
    figures = {"precision", "recall", "f1", "exact_accuracy", "views", "label_views", "cover_precision"}
    figures |= {"cover_recall", "cover_f1", "cover_exact", "covers_u"}
    every = [*report["decodings"].values(), *report["view_state_prior"].values()]
    assert all(set(scores) == figures for scores in every)
    assert 0 < report["samples"] < 200 and 0.0 <= report["decodings"]["size"]["cover_f1"] <= 1.0
    # --split train: the samples the run trained on
    assert (
        main(["eval", "--data", dataset_url, "--checkpoint", str(out / "best.pt"), "--split", "train", "--json"]) == 0
    )
    trained_on = json.loads(capsys.readouterr().out)
    assert main(["eval", "--data", dataset_url, "--checkpoint", str(out / "best.pt"), "--decoding", "topk=3"]) == 0
    table = capsys.readouterr().out
    assert table.startswith("| planner | decoding | samples | precision | recall | F1 | exact set | nearest-cover F1 |")
    network, *priors = table.splitlines()[2:]
    assert network.startswith("| network | topk=3 |")
    assert int(network.split("|")[3]) == report["samples"] + trained_on["samples"], "train + val = all"
    assert float(network.split("|")[10]) == 3.0, "topk=3 always takes three views"
    assert [row.split("|")[1:3] for row in priors] == [
        [" view-state prior ", " threshold 0.5 "],
        [" view-state prior ", " size "],
    ]


def test_a_version_1_dataset_trains_on_labels_and_refuses_ambiguity_targets(
    v1_dataset_url: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    args = ["train", "--data", v1_dataset_url, "--out", str(out), "--batch-size", "32", "--epochs", "1"]
    assert main([*args, "--target", "mincover"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "datagen shards relabel" in err[0]
    assert main(args) == 2  # the default target (mincover) needs the covers too
    assert "datagen shards relabel" in capsys.readouterr().err
    assert main([*args, "--target", "label"]) == 0
    assert "best validation F1 (label bits, p > 0.5)" in capsys.readouterr().err
    assert main(["eval", "--data", v1_dataset_url, "--checkpoint", str(out / "best.pt")]) == 0
    network = capsys.readouterr().out.splitlines()[2].split("|")
    assert network[2].strip() == "threshold 0.5" and network[8].strip() == "-" and network[9].strip() == "-"


def test_sweep_lambda_prints_the_table_shape(dataset_url: str, tmp_path: Path, capsys) -> None:
    args = ["sweep-lambda", "--data", dataset_url, "--out", str(tmp_path), "--epochs", "1", "--lambdas", "0.75,2"]
    assert main([*args, "--batch-size", "64"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "| lambda | recall | precision | F1 | best epoch |"
    assert [line.split("|")[1].strip() for line in lines[2:]] == ["0.75", "2"]
    assert (tmp_path / "lambda-0.75" / "best.pt").is_file() and (tmp_path / "lambda-2" / "best.pt").is_file()


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["train", "--data", "/no/such/dataset", "--out", "OUT"], "/no/such/dataset"),
        (["eval", "--data", "DATA", "--checkpoint", "/no/such.pt"], "checkpoint not found"),
        (["train", "--data", "DATA", "--out", "OUT", "--epochs", "0"], "epochs 0 must be >= 1"),
        (["train", "--data", "DATA", "--out", "OUT", "--device", "cuda:7"], None),
        (["train", "--data", "DATA", "--out", "OUT", "--max-objects", "9"], "training side holds 3 objects"),
        (["train", "--data", "DATA", "--out", "OUT", "--sample-fraction", "1.5"], "must lie in (0, 1]"),
        (["eval", "--data", "DATA", "--checkpoint", "CKPT", "--decoding", "nope"], "--decoding: unknown decoding"),
    ],
)
def test_user_errors_are_one_line(
    args: list[str], needle: str | None, dataset_url: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    if "CKPT" in args:  # any checkpoint: the decoding is refused before the dataset is read
        train(TrainOptions(data=dataset_url, out=tmp_path / "run", epochs=1, batch_size=64))
    names = {"DATA": dataset_url, "OUT": str(tmp_path / "out"), "CKPT": str(tmp_path / "run" / "best.pt")}
    resolved = [names.get(a, a) for a in args]
    code = main(resolved)
    # An error found after reading the samples follows the progress note "read N samples ..."
    err = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("read ")]
    if needle is None and code == 0:
        pytest.skip("CUDA is available here")
    assert code == 2
    assert len(err) == 1 and err[0].startswith("error: ")
    if needle:
        assert needle in err[0]


def test_a_grid_network_trains_and_evaluates_from_the_command_line(
    dataset_url: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--network nbvnet` (its default target: the best next view) prints its best-view accuracy every
    epoch, its training fit with --fit-rows, and `osvp eval` reads the grids its checkpoint needs."""
    out = tmp_path / "nbvnet"
    args = ["train", "--data", dataset_url, "--out", str(out), "--epochs", "1", "--network", "nbvnet"]
    assert main([*args, "--fit-rows", "16"]) == 0
    err = capsys.readouterr().err
    assert "epoch 1/1" in err and " best view " in err and "gain error" not in err
    assert main(["eval", "--data", dataset_url, "--checkpoint", str(out / "best.pt"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["target"] == "best_view" and set(report["next_view"]) == {"best_view_accuracy", "chosen_gain_ratio"}
    assert 0.0 <= report["next_view"]["best_view_accuracy"] <= 1.0
    assert 0.0 <= report["next_view"]["chosen_gain_ratio"] <= 1.0
    assert main(["eval", "--data", dataset_url, "--checkpoint", str(out / "best.pt")]) == 0
    assert capsys.readouterr().out.startswith("next-best-view planner (best_view), ")


def test_network_help_is_written_from_the_registry(capsys: pytest.CaptureFixture[str]) -> None:
    """`osvp train --help` names every registered network family with what it is (no list by hand)."""
    from osvp.architectures import ARCHITECTURES

    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for name, family in ARCHITECTURES.items():
        assert f"{name}: {' '.join(family.summary.split())}" in text
