"""docs/extending.md's examples, run as written: each ``# example: KIND`` block registers one entry, which
then works where its kind is used; the entries are removed afterwards."""

from __future__ import annotations

import re
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType, SimpleNamespace

import numpy as np
import pytest
from support import storage as fx
from typer.testing import CliRunner

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "extending.md"
BLOCK = re.compile(r"```python\n# example: (?P<kind>[^\n]+)\n(?P<code>.*?)```", re.S)


def examples() -> dict[str, str]:
    return {match["kind"]: match["code"] for match in BLOCK.finditer(DOC.read_text())}


@pytest.fixture
def run_example() -> Iterator[Callable[[str], dict[str, object]]]:
    """Runs one example in a fresh namespace; every registry entry it adds is removed at the end."""
    from schemas import registry

    before = {id(kind): set(kind.names(plugins=False)) for kind in registry.KINDS}

    modules: list[str] = []

    def run(kind: str) -> dict[str, object]:
        """The example as the module a plug-in would be (dataclasses look their module up)."""
        module = ModuleType(f"extending_{kind.replace(' ', '_')}")
        sys.modules[module.__name__] = module
        modules.append(module.__name__)
        exec(compile(examples()[kind], f"{DOC}:{kind}", "exec"), module.__dict__)
        return module.__dict__

    yield run
    for name in modules:
        sys.modules.pop(name, None)
    for kind in registry.KINDS:
        for name in set(kind.names(plugins=False)) - before.get(id(kind), set()):
            kind.unregister(name)


def test_every_kind_of_the_table_has_an_example() -> None:
    assert set(examples()) == {
        "refiner",
        "objective",
        "sample field",
        "export layout",
        "planner",
        "network family and target",
    }


def test_the_refiner_example(run_example: Callable[[str], dict[str, object]]) -> None:
    from datagen.pipeline.refine.factory import make_refiner
    from schemas.config import GenerationConfig

    namespace = run_example("refiner")
    config = GenerationConfig(refiner="fill")
    assert isinstance(make_refiner(config), namespace["FillRefiner"])  # type: ignore[arg-type]


def test_the_objective_example(run_example: Callable[[str], dict[str, object]]) -> None:
    from datagen.pipeline.objectives import task_labeller
    from schemas.config import GenerationConfig

    run_example("objective")
    config = GenerationConfig(label_objective="first_new_view", refiner="none")
    visible = (np.array([1, 2]), np.array([2, 3]), np.array([1]), np.array([4]))
    labeller = task_labeller(visible, None, config)
    assert labeller.label(0b0001).label == 0b0010  # view 1 sees key 3, new to view 0


def test_the_sample_field_example(run_example: Callable[[str], dict[str, object]], tmp_path: Path) -> None:
    from storage import open_dataset
    from storage.readers import load_memory

    run_example("sample field")
    fx.build_dataset(str(tmp_path / "ds"), finalise_index=True)
    memory = load_memory(str(tmp_path / "ds"))
    batch = memory.batch(np.arange(len(memory)), 64, seed=0, epoch=0)
    labels = open_dataset(str(tmp_path / "ds")).index.column("label").to_pylist()
    rows = np.asarray(batch.index).tolist()
    assert np.asarray(batch.field("label_size")).tolist() == [bin(int(labels[row])).count("1") for row in rows]


def test_the_export_layout_example(
    run_example: Callable[[str], dict[str, object]], tmp_path: Path, runner: CliRunner
) -> None:
    from datagen.cli.main import app
    from storage import open_dataset
    from storage.export import export

    run_example("export layout")
    url = str(tmp_path / "ds")
    fx.build_dataset(url, finalise_index=True)
    done = export("views", url, tmp_path / "out")
    written = sorted((tmp_path / "out").rglob("views_*.txt"))
    assert done.written == len(written) == len(open_dataset(url)) > 0
    assert all(line.split() == sorted(line.split(), key=int) for line in (p.read_text() for p in written))
    # the command takes it by name and lists it
    exported = runner.invoke(app, ["shards", "export", url, str(tmp_path / "cli"), "--layout", "views"])
    assert exported.exit_code == 0, exported.output
    assert len(list((tmp_path / "cli").rglob("views_*.txt"))) == len(written)
    shown = runner.invoke(app, ["shards", "export", "--help"], env={"COLUMNS": "4000"})
    assert "'views': each sample's label as a line of view ids" in " ".join(shown.stdout.replace("│", " ").split())


def test_the_planner_example(run_example: Callable[[str], dict[str, object]]) -> None:
    from datagen.evaluate.planners import make_planner

    run_example("planner")
    planner = make_planner("lowest:3")
    situation = SimpleNamespace(scene=SimpleNamespace(num_views=32), initial_view=0)
    assert planner.plan(situation).views == (1, 2)  # type: ignore[arg-type]


def test_the_network_and_target_example(run_example: Callable[[str], dict[str, object]]) -> None:
    torch = pytest.importorskip("torch")
    from osvp.architectures import architecture
    from osvp.loss import target_loss

    run_example("network family and target")
    family = architecture("meanview")
    network = family.build(family.preset("small"), 32)
    logits = network(torch.zeros(2, 256, 3), torch.zeros(2, 32))
    assert logits.shape == (2, 32) and family.default_target == "label_mse"
    batch = SimpleNamespace(label=torch.ones(2, 32))
    assert float(target_loss("label_mse", torch.zeros(2, 32), batch, 1.0)) == pytest.approx(0.25)
