"""The planners shipped inside osvp (`osvp.shipped`): each checkpoint is the file its sha256 names, has
its training card, loads and plays one object through ``datagen evaluate --planner shipped:NAME`` in
seconds with no training and no --config (it images as its training data was); a missing or damaged
checkpoint, and a --config that images otherwise, are one error line each."""

from __future__ import annotations

import hashlib
import importlib.util
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from datagen.cli.main import app
from datagen.evaluate import scored

pytestmark = pytest.mark.skipif(importlib.util.find_spec("osvp") is None, reason="the osvp package is not installed")


@pytest.fixture(autouse=True)
def fresh_scorers() -> None:
    """Each test builds its scorers again (the evaluation keeps one per plug-in and argument)."""
    scored._SCORERS.clear()


@pytest.fixture
def capsule(tmp_path: Path) -> Path:
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    return objects


def names() -> list[str]:
    from osvp.shipped import SHIPPED

    return sorted(SHIPPED)


@pytest.mark.parametrize("name", names())
def test_a_shipped_planner_is_its_hashed_file_with_a_card_and_plays_an_object(
    name: str, capsule: Path, runner: CliRunner
) -> None:
    from osvp.checkpoint import load_checkpoint
    from osvp.shipped import SHIPPED

    planner = SHIPPED[name]
    assert hashlib.sha256(planner.path.read_bytes()).hexdigest() == planner.sha256
    assert planner.path.stat().st_size < 8_000_000  # small enough to ship in the wheel
    card = planner.card.read_text()
    assert planner.sha256 in card and f"shipped:{name}" in card
    recorded = load_checkpoint(planner.path).generation_config
    assert recorded is not None  # the config it expects travels with it
    result = runner.invoke(
        app,
        [
            "evaluate",
            "--objects",
            str(capsule),
            "-p",
            f"shipped:{name}",
            "-p",
            "gain",
            "-p",
            "spread",
            "--budget-views",
            "4",
            "--margins",
            "2,3,4",
            "--workers",
            "1",
        ],
    )
    assert result.exit_code == 0, result.output
    assert f"imaging as planner shipped:{name} was trained" in result.output
    assert f"| all | shipped:{name}" in result.output


def test_shipped_planners_are_listed_in_evaluate_help(runner: CliRunner) -> None:
    result = runner.invoke(app, ["evaluate", "--help"], terminal_width=400)
    assert result.exit_code == 0
    text = " ".join(result.output.split())
    for name in names():
        assert f"shipped:{name}" in text


@pytest.mark.parametrize("damage", ["missing", "truncated", "replaced"])
def test_a_missing_or_damaged_checkpoint_is_one_line(
    damage: str, capsule: Path, tmp_path: Path, runner: CliRunner, monkeypatch: pytest.MonkeyPatch
) -> None:
    import osvp.shipped

    folder = tmp_path / "shipped"
    shutil.copytree(osvp.shipped.HERE, folder, ignore=shutil.ignore_patterns("*.py", "__pycache__"))
    checkpoint = folder / "nbv.pt"
    if damage == "missing":
        checkpoint.unlink()
    elif damage == "truncated":
        checkpoint.write_bytes(checkpoint.read_bytes()[:1000])
    else:
        data = bytearray(checkpoint.read_bytes())
        data[len(data) // 2] ^= 0xFF
        checkpoint.write_bytes(bytes(data))
    monkeypatch.setattr(osvp.shipped, "HERE", folder)
    result = runner.invoke(app, ["evaluate", "--objects", str(capsule), "-p", "shipped:nbv", "-p", "gain"])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: shipped:nbv:"), result.output
    assert ("missing" if damage == "missing" else "damaged or replaced") in lines[0]
    assert "reinstall osvp" in lines[0]


def test_an_unknown_shipped_planner_names_the_choices(capsule: Path, runner: CliRunner) -> None:
    result = runner.invoke(app, ["evaluate", "--objects", str(capsule), "-p", "shipped:nope", "-p", "gain"])
    assert result.exit_code == 2
    assert "no shipped planner 'nope'" in result.output and "shipped:nbv" in result.output


def test_a_config_that_images_otherwise_is_refused_in_one_line(
    capsule: Path, tmp_path: Path, runner: CliRunner
) -> None:
    config = tmp_path / "coarse.toml"
    config.write_text("voxel_size = 0.012\nrefiner = 'none'\n")
    result = runner.invoke(
        app, ["evaluate", "--objects", str(capsule), "-p", "shipped:nbv", "-p", "gain", "--config", str(config)]
    )
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "voxel_size 0.002" in lines[0] and "voxel_size 0.012" in lines[0], result.output
    same = tmp_path / "same.toml"
    same.write_text("refiner = 'none'\nrotations = 2\n")  # images alike: accepted
    result = runner.invoke(
        app,
        [
            "evaluate",
            "--objects",
            str(capsule),
            "-p",
            "shipped:nbv",
            "-p",
            "gain",
            "--config",
            str(same),
            "--budget-views",
            "3",
            "--workers",
            "1",
        ],
    )
    assert result.exit_code == 0, result.output
