"""A network family and a training target added from this test module alone (issue 51): one
`register_architecture` and one `register_target` call, no file of osvp touched. The toy network trains
on the toy target from the command line, its checkpoint evaluates (`osvp eval`) and plays in `datagen
evaluate` as ``osvp:FILE``; both are listed by ``osvp train --help``; an installed package adds a target
through the entry-point group ``osvp.targets``.

- network ``meanview``: the cloud's mean and spread (6 numbers) and the view state, one linear layer;
- target ``label_mse``: the label bits regressed by the sigmoid of the logits (mean squared error).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
from osvp.architectures import ARCHITECTURES, Architecture, Preset, register_architecture
from osvp.cli import main
from osvp.loss import TARGET_REGISTRY, TargetBatch, register_target, targets
from torch import nn

NETWORK, TARGET = "meanview", "label_mse"


@dataclass(frozen=True)
class MeanPreset:
    name: str = "small"
    num_points: int = 256

    def as_dict(self) -> dict[str, object]:
        return {"name": self.name, "num_points": self.num_points}


def parse_preset(data: dict[str, object]) -> Preset:
    return MeanPreset(str(data["name"]), int(str(data["num_points"])))


class MeanView(nn.Module):
    def __init__(self, num_views: int) -> None:
        super().__init__()
        self.linear = nn.Linear(6 + num_views, num_views)

    def forward(self, points: torch.Tensor, view_state: torch.Tensor) -> torch.Tensor:
        summary = torch.cat([points.mean(dim=1), points.std(dim=1)], dim=1)
        logits: torch.Tensor = self.linear(torch.cat([summary, view_state], dim=1))
        return logits


def label_mse(logits: torch.Tensor, batch: TargetBatch, lambda_: float) -> torch.Tensor:
    return torch.mean((torch.sigmoid(logits) - batch.label.to(logits.device)) ** 2)


@pytest.fixture(scope="module", autouse=True)
def toys() -> Iterator[None]:
    presets = {"small": MeanPreset("small", 256), "paper": MeanPreset("paper", 512)}
    register_architecture(
        Architecture(
            NETWORK, "points", presets, parse_preset, lambda p, n: MeanView(n), TARGET, "the cloud's mean and spread"
        )
    )
    register_target(TARGET, reads=("label",))(label_mse)
    yield
    ARCHITECTURES.unregister(NETWORK)
    TARGET_REGISTRY.unregister(TARGET)


def test_the_toys_are_listed_and_declare_what_they_read(capsys: pytest.CaptureFixture[str]) -> None:
    assert TARGET in targets() and not TARGET_REGISTRY[TARGET].needs_ties and TARGET_REGISTRY[TARGET].since == 1
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert f"{NETWORK}: the cloud's mean and spread" in text and TARGET in text
    with pytest.raises(ValueError, match="reads nothing_here, which no sample field is"):
        register_target("broken", reads=("nothing_here",))


def test_the_toy_network_trains_on_the_toy_target_evaluates_and_plays(
    dataset_url: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    args = ["train", "--data", dataset_url, "--out", str(out), "--epochs", "2", "--network", NETWORK]
    assert main(args) == 0  # the family's default target: the toy one
    assert "epoch 2/2" in capsys.readouterr().err
    assert main(["eval", "--data", dataset_url, "--checkpoint", str(out / "best.pt"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["target"] == TARGET and report["samples"] > 0
    assert 0.0 <= report["decodings"]["size"]["f1"] <= 1.0
    pytest.importorskip("datagen")
    from typer.testing import CliRunner

    from datagen.cli.main import app

    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    planner = f"osvp+size:{out / 'best.pt'}"
    evaluate = ["evaluate", "--objects", str(objects), "-p", planner, "--rotations", "0", "--workers", "1"]
    margins = ["-p", "gain", "-p", "spread", "--budget-views", "3", "--margins", "2,3"]
    played = CliRunner().invoke(app, [*evaluate, *margins, "--initial-views", "0"])
    assert played.exit_code == 0, played.output
    assert f"| all | {planner}" in played.output


TARGET_PACKAGE = '''
"""A third-party training target: the label bits by mean absolute error."""
import torch

from osvp.loss import Target


def label_mae(logits, batch, lambda_):
    return torch.mean(torch.abs(torch.sigmoid(logits) - batch.label.to(logits.device)))


TARGET = Target("label_mae", label_mae, reads=("label",))
'''


def test_an_installed_target_is_found_through_its_entry_point(
    dataset_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    site = tmp_path / "site"
    site.mkdir()
    (site / "toy_target.py").write_text(TARGET_PACKAGE)
    info = site / "toy_target-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-target\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[osvp.targets]\nlabel_mae = toy_target:TARGET\n")
    monkeypatch.syspath_prepend(str(site))
    TARGET_REGISTRY.forget_plugins()
    try:
        assert "label_mae" in targets()
        assert [e.source for e in TARGET_REGISTRY.entries() if e.name == "label_mae"] == ["distribution toy-target 0.1"]
        out = tmp_path / "mae"
        args = ["train", "--data", dataset_url, "--out", str(out), "--epochs", "1", "--target", "label_mae"]
        assert main(args) == 0
        assert main(["eval", "--data", dataset_url, "--checkpoint", str(out / "best.pt"), "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["target"] == "label_mae"
    finally:
        monkeypatch.undo()
        sys.modules.pop("toy_target", None)
        TARGET_REGISTRY.forget_plugins()
