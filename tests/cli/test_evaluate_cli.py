"""`datagen evaluate` from the command line: tables, JSON, pictures, budgets and one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from PIL import Image
from typer.testing import CliRunner

from datagen.cli.main import app

BROKEN_MESH = b"v 0 0 0\nv 1 0 0\nf 1 2 9\n" + bytes(range(256)) * 4


@pytest.fixture
def objects(tmp_path: Path) -> Path:
    (tmp_path / "broken.obj").write_bytes(BROKEN_MESH)
    path = tmp_path / "objects.txt"
    path.write_text(f"builtin:capsule\n{tmp_path / 'broken.obj'}\nbuiltin:cone\n")
    return path


@pytest.fixture
def config(tmp_path: Path) -> Path:
    path = tmp_path / "config.toml"
    path.write_text('refiner = "none"\nrotations = 4\n')
    return path


def evaluate(runner: CliRunner, *args: str):
    return runner.invoke(app, ["evaluate", "--workers", "1", *args])


def errors(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("error:")]


def test_json_rows_runs_and_the_broken_mesh_as_one_line(runner: CliRunner, objects: Path, config: Path) -> None:
    result = evaluate(
        runner,
        *("--objects", str(objects), "--config", str(config), "--initial-views", "0,5", "--rotations", "0,3"),
        *("-p", "oracle", "-p", "greedy:3", "-p", "random", "-p", "all", "--json"),
    )
    assert result.exit_code == 1, result.output  # ran, one object failed
    (line,) = errors(result.stderr)
    assert "broken.obj" in line and "Traceback" not in result.output
    report = json.loads(result.stdout)
    rows = {(row["refiner"], row["planner"]): row for row in report["rows"]}
    assert set(rows) == {("none", "oracle"), ("-", "greedy:3"), ("none", "random"), ("-", "all")}
    assert all(row["objects"] == 2 and row["runs"] == 2 * 2 * 2 for row in rows.values())
    assert rows[("-", "all")]["coverage"] == 100.0 and rows[("-", "all")]["coverage_std"] == 0.0
    assert rows[("-", "greedy:3")]["views"] == 3.0
    assert rows[("none", "random")]["views"] == rows[("none", "oracle")]["views"]
    runs = report["runs"]
    assert len(runs) == 4 * 8
    assert {r["initial_view"] for r in runs} == {0, 5} and {r["rotation"] for r in runs} == {0, 3}
    for run in runs:
        assert run["visited"][0] == run["initial_view"]
        assert run["views"] == len(run["visited"]) and len(run["step_metres"]) == run["views"] - 1
        assert run["movement"] == pytest.approx(sum(run["step_metres"]), abs=1e-5)
    assert report["failures"] == [line.removeprefix("error: ")]


def test_table_per_object_and_pictures(runner: CliRunner, objects: Path, config: Path, tmp_path: Path) -> None:
    png = tmp_path / "figures" / "coverage.png"
    result = evaluate(
        runner,
        *("--objects", str(objects), "--config", str(config), "-p", "oracle", "-p", "greedy"),
        *("--per-object", "--png", str(png)),
    )
    assert result.exit_code == 1, result.output
    lines = result.stdout.splitlines()
    assert lines[0].startswith("| refiner | planner | coverage %")
    assert any(line.startswith("| capsule | none | oracle |") for line in lines)
    assert any(line.startswith("| cone | - | greedy |") for line in lines)
    pictures = sorted(png.parent.glob("*.png"))
    assert [p.name for p in pictures] == ["coverage-00-capsule.png", "coverage-02-cone.png", "coverage.png"]
    for picture in pictures:
        with Image.open(picture) as image:
            assert image.width > 200 and image.height > 200


def test_budgets_cut_the_runs(runner: CliRunner, objects: Path, config: Path) -> None:
    result = evaluate(
        runner,
        *("--objects", str(objects), "--config", str(config), "-p", "all", "-p", "greedy"),
        *("--budget-views", "4", "--budget-moves", "0.9", "--json"),
    )
    runs = json.loads(result.stdout)["runs"]
    assert runs and all(r["views"] <= 4 and r["movement"] <= 0.9 + 1e-9 for r in runs)


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (("-p", "genius"), "unknown planner 'genius'"),
        (("-p", "osvp:/no/such/model.pt"), "checkpoint not found"),
        (("-p", "greedy:0"), "K must be"),
        (("-p", "all", "--budget-views", "0"), "--budget-views 0"),
        (("-p", "all", "--budget-moves", "-1"), "--budget-moves -1.0"),
        (("-p", "all", "--rotations", "9"), "--rotations '9'"),
        # refused before any work: here before the --fixed-from dataset would be read (issue 42)
        (("-p", "fixed:4", "--fixed-from", "/no/such/dataset", "--rotations", "0,4"), "--rotations '0,4'"),
        (("-p", "all", "--initial-views", "32"), "--initial-views '32'"),
        (("-p", "all", "--refiner", "magic"), "unknown refiner 'magic'"),
    ],
)
def test_bad_arguments_are_one_error_line(
    runner: CliRunner, objects: Path, config: Path, args: tuple[str, ...], needle: str
) -> None:
    result = evaluate(runner, "--objects", str(objects), "--config", str(config), *args)
    assert result.exit_code == 2, result.output
    (line,) = errors(result.stderr)
    assert needle in line and result.stdout == ""


def test_missing_objects_file_is_one_error_line(runner: CliRunner, tmp_path: Path) -> None:
    result = evaluate(runner, "--objects", str(tmp_path / "none.txt"), "-p", "all")
    assert result.exit_code == 2
    (line,) = errors(result.stderr)
    assert "objects file not found" in line


def test_help_is_written_from_the_registries(
    runner: CliRunner, monkeypatch: pytest.MonkeyPatch, request: pytest.FixtureRequest
) -> None:
    """`--planner` and `--refiner` list what the registries hold (issue 42: no list kept by hand beside
    them), a planner registered later included."""
    from datagen.evaluate import planners
    from schemas.refiners import REFINERS

    planners.PLANNERS.register("toy", planners.PlannerKind("toy", lambda spec, context: None, "toy, toy:K"))
    request.addfinalizer(lambda: planners.PLANNERS.unregister("toy"))
    monkeypatch.setenv("COLUMNS", "4000")
    result = runner.invoke(app, ["evaluate", "--help"])
    assert result.exit_code == 0
    text = " ".join(result.stdout.replace("│", " ").split())
    for kind in planners.PLANNERS.values(plugins=False):
        assert kind.usage in text, kind.usage
    assert "toy, toy:K" in text and all(name in text for name in REFINERS)
