"""`osvp train | eval | sweep-lambda` end to end on the small dataset; user errors are one line, exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from osvp.cli import main


def test_train_then_eval(dataset_url: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    assert main(["train", "--data", dataset_url, "--out", str(out), "--epochs", "2", "--batch-size", "32"]) == 0
    err = capsys.readouterr().err
    assert "epoch 2/2" in err and "best validation F1" in err
    assert sorted(p.name for p in out.iterdir()) == ["best.pt", "curves.png", "last.pt", "metrics.csv"]
    assert main(["eval", "--data", dataset_url, "--checkpoint", str(out / "best.pt"), "--split", "val", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert set(report) == {"samples", "loss", "precision", "recall", "f1", "exact_accuracy", "view_state_prior"}
    assert set(report["view_state_prior"]) == {"precision", "recall", "f1", "exact_accuracy"}
    assert 0 < report["samples"] < 200 and 0.0 <= report["f1"] <= 1.0
    assert (
        main(["eval", "--data", dataset_url, "--checkpoint", str(out / "best.pt"), "--split", "train", "--json"]) == 0
    )
    trained_on = json.loads(capsys.readouterr().out)
    assert main(["eval", "--data", dataset_url, "--checkpoint", str(out / "best.pt")]) == 0
    table = capsys.readouterr().out
    assert table.startswith("| planner | samples | precision | recall | F1 | exact set | SCLoss |")
    network, prior = table.splitlines()[2:4]
    assert network.startswith("| network |") and prior.startswith("| view-state prior |")
    assert int(network.split("|")[2]) == report["samples"] + trained_on["samples"], "train + val = all"


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
    ],
)
def test_user_errors_are_one_line(
    args: list[str], needle: str | None, dataset_url: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    resolved = [dataset_url if a == "DATA" else str(tmp_path / "out") if a == "OUT" else a for a in args]
    code = main(resolved)
    err = capsys.readouterr().err.strip().splitlines()
    if needle is None and code == 0:
        pytest.skip("CUDA is available here")
    assert code == 2
    assert len(err) == 1 and err[0].startswith("error: ")
    if needle:
        assert needle in err[0]
