"""Planner plugins (`schemas.planning`): a distribution registers a `ScorerFactory` in the entry-point group
``datagen.planners`` and ``--planner NAME:ARG`` plans with it; osvp is one such plugin. A plugin's scorer is
built once per process, however many objects; a missing, unknown or broken plugin is one error line."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from collections.abc import Callable, Iterator
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest
from support.plugins import forget_plugins

from datagen.errors import PlannerError
from datagen.evaluate import scored as scored_module
from datagen.evaluate.planners import installed_plugins, lookup_planner, make_planner, planner_help, planner_kinds
from datagen.evaluate.run import EvaluationSpec, evaluate
from datagen.evaluate.scored import ScoredPlanner
from datagen.evaluate.situation import RefinedScene, Situation
from schemas.config import GenerationConfig
from schemas.planning import PLANNER_ENTRY_POINTS, DecodingScorer, ViewScorer

TOY_MODULE = '''
"""A third-party planner: prefers low view ids (probability 0.9 below K, 0.1 from K on) for ``toy:K``."""
import os

import numpy as np


class IndexScorer:
    def __init__(self, below):
        self.below = below

    def view_probabilities(self, points, view_state):
        return np.where(np.arange(np.asarray(view_state).size) < self.below, 0.9, 0.1)


def make(argument):
    count = os.environ.get("TOY_COUNT")
    if count:  # one line per load, naming the process
        with open(count, "a") as file:
            file.write(f"{os.getpid()}\\n")
    if not argument.isdigit():
        raise ValueError(f"toy:{argument}: give a whole number of views")
    return IndexScorer(int(argument))
'''

Install = Callable[..., Path]


@pytest.fixture
def install(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Install]:
    """``install(dist, module, source, entry=...)``: a distribution on sys.path (a ``.dist-info`` beside the
    module, as pip lays it out), whose entry point ``entry`` (default: the dist's name) is ``module:make``;
    the scorer cache starts empty and the module is forgotten afterwards."""
    site = tmp_path / "site"
    site.mkdir()
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setattr(scored_module, "_SCORERS", {})
    modules: list[str] = []

    def add(dist: str, module: str, source: str, entry: str | None = None) -> Path:
        (site / f"{module}.py").write_text(source)
        info = site / f"{dist}-0.1.dist-info"
        info.mkdir()
        (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
        (info / "entry_points.txt").write_text(f"[{PLANNER_ENTRY_POINTS}]\n{entry or dist} = {module}:make\n")
        modules.append(module)
        forget_plugins()  # the registries read the installed entry points again
        return site

    yield add
    for module in modules:
        sys.modules.pop(module, None)
    monkeypatch.undo()
    forget_plugins()


def test_the_osvp_entry_point_is_registered() -> None:
    if importlib.util.find_spec("osvp") is None:
        pytest.skip("the osvp package is not installed")
    (plugin,) = [p for p in entry_points(group=PLANNER_ENTRY_POINTS) if p.name == "osvp"]
    assert plugin.value == "osvp.planning:load_scorer"
    assert plugin.dist is not None and plugin.dist.name == "osvp"
    from osvp.planning import CheckpointScorer, load_scorer

    assert plugin.load() is load_scorer and installed_plugins()["osvp"].source.startswith("distribution osvp ")
    assert issubclass(CheckpointScorer, DecodingScorer)
    assert "osvp:ARG" in planner_help()


def test_a_plugin_plans_and_unknown_names_list_it(install: Install, real: RefinedScene) -> None:
    install("toy-planner", "toy_planner", TOY_MODULE, entry="toy")
    # one lookup finds a third-party planner (through its entry point) and a built-in alike
    toy, greedy = lookup_planner("toy"), lookup_planner("greedy")
    assert (toy.name, toy.usage, toy.source) == ("toy", "toy:ARG", "distribution toy-planner 0.1")
    assert (greedy.name, greedy.source) == ("greedy", "built-in") and {"toy", "greedy"} <= set(planner_kinds())
    planner = make_planner("toy:5")
    assert isinstance(planner, ScoredPlanner) and planner.name == "toy:5" and planner.uses_refinement
    assert isinstance(planner.scorer, ViewScorer) and not isinstance(planner.scorer, DecodingScorer)
    assert planner.plan(Situation(real, 2)).views == (0, 1, 3, 4)
    with pytest.raises(PlannerError) as info:
        make_planner("nope:1")
    message = str(info.value)
    assert message.startswith("unknown planner 'nope:1'; choose oracle, oracle:SETTING=V") and "\n" not in message
    assert "toy:ARG" in message
    with pytest.raises(PlannerError, match=r"^planner 'toy:x': toy:x: give a whole number of views$"):
        make_planner("toy:x")
    with pytest.raises(PlannerError, match=r"this scorer has no decodings; drop '\+size'"):
        make_planner("toy+size:5")


def test_a_broken_plugin_is_one_line_naming_its_distribution(install: Install) -> None:
    install("broken-planner", "broken_planner", "import no_such_module_anywhere\n", entry="broken")
    install("odd-planner", "odd_planner", "def make(argument):\n    return argument\n", entry="odd")
    with pytest.raises(PlannerError) as info:
        make_planner("broken:x")
    message = str(info.value)
    assert "\n" not in message
    assert "'broken' (broken_planner:make, distribution broken-planner 0.1) cannot be imported" in message
    assert message.endswith("ModuleNotFoundError: No module named 'no_such_module_anywhere'")
    with pytest.raises(PlannerError, match=r"plugin 'odd' .* returned a str, not a scorer with view_probabilities"):
        make_planner("odd:x")


def test_a_plugin_that_is_not_installed_is_an_unknown_planner(no_plugins: None) -> None:
    """No name is special: without its entry point, osvp is unknown like any other plugin."""
    with pytest.raises(PlannerError) as info:
        make_planner("osvp:run/best.pt")
    message = str(info.value)
    assert message.startswith("unknown planner 'osvp:run/best.pt'; choose oracle") and "\n" not in message
    assert message.endswith("(none installed in 'datagen.planners')")


@pytest.mark.parametrize("workers", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_a_plugin_is_loaded_once_per_process(
    install: Install, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, workers: int
) -> None:
    """Three objects: one load in the calling process, and at most one in each worker (workers=2 spawns)."""
    install("toy-planner", "toy_planner", TOY_MODULE, entry="toy")
    count = tmp_path / "loads.txt"
    monkeypatch.setenv("TOY_COUNT", str(count))
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\nbuiltin:cone\nbuiltin:bowl\n")
    spec = EvaluationSpec(planners=("toy:5",), refiners=("none",), rotations=(0,), initial_views=(2,))
    result = evaluate(objects, GenerationConfig(refiner="none"), spec, workers=workers)
    assert not result.all_failures
    assert len(result.episodes) == 3 and all(sorted(e.planned) == [0, 1, 3, 4] for e in result.episodes)
    loads = count.read_text().split()
    assert loads.count(str(os.getpid())) == 1
    assert len(loads) == len(set(loads)) <= 1 + (workers if workers > 1 else 0)


@pytest.mark.slow
def test_a_pip_installed_distribution_is_found_by_the_command(tmp_path: Path) -> None:
    """A third-party project, built and installed by pip into its own folder, plans through
    ``datagen evaluate --planner toy:5`` with nothing but that folder on PYTHONPATH."""
    project = tmp_path / "toy"
    project.mkdir()
    (project / "toy_planner.py").write_text(TOY_MODULE)
    (project / "pyproject.toml").write_text(
        textwrap.dedent(
            """
            [build-system]
            requires = ["setuptools>=68"]
            build-backend = "setuptools.build_meta"

            [project]
            name = "toy-planner"
            version = "0.1.0"

            [project.entry-points."datagen.planners"]
            toy = "toy_planner:make"

            [tool.setuptools]
            py-modules = ["toy_planner"]
            """
        )
    )
    site = tmp_path / "site"
    pip = [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index"]
    built = subprocess.run([*pip, "--target", str(site), str(project)], capture_output=True, text=True, cwd=tmp_path)
    assert built.returncode == 0, built.stderr
    assert (site / "toy_planner.py").is_file()
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    env = {**os.environ, "PYTHONPATH": str(site), "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "datagen.cli.main", "evaluate", "--objects", str(objects), "--workers", "1"]
    options = ["--refiner", "none", "--initial-views", "2", "-p", "toy:5", "-p", "oracle", "--json"]
    done = subprocess.run([*command, *options], capture_output=True, text=True, cwd=tmp_path, env=env)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert [row["planner"] for row in report["rows"]] == ["toy:5", "oracle"]
    (run,) = [r for r in report["runs"] if r["planner"] == "toy:5"]
    assert sorted(run["planned"]) == [0, 1, 3, 4]
    assert run["visited"][0] == 2 and sorted(run["visited"]) == [0, 1, 2, 3, 4]
    wide = {**env, "COLUMNS": "400"}  # the help lists installed plug-ins from the registry: one line here
    help_text = subprocess.run([*command, "--help"], capture_output=True, text=True, cwd=tmp_path, env=wide)
    assert "toy:ARG" in " ".join(help_text.stdout.split())


def test_probabilities_reach_the_plan(install: Install, real: RefinedScene) -> None:
    install("toy-planner", "toy_planner", TOY_MODULE, entry="toy")
    plan = make_planner("toy:3").plan(Situation(real, 0))
    assert plan.views == (1, 2)
    assert plan.probabilities is not None and np.array_equal(plan.probabilities[:4], [0.9, 0.9, 0.9, 0.1])
