"""A trainer's machine: a fresh virtual environment with `pip install ./reader ./osvp` (no editable
install, no datagen) gets the reader and the schemas with their light dependencies only, and trains on
a dataset made with the default POCO refiner.

The dataset's identity (its config hash) comes from its ``dataset.json``. It must never be recomputed
there: for a POCO dataset that would hash the shipped weights file, which is found through the
datagen package and so is absent on a trainer's machine.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]

GENERATOR_ONLY = ("ray", "embreex", "trimesh", "highspy", "open3d", "manifold3d", "datagen")
"""Distributions a trainer's install must not pull (datagen itself included)."""
LIGHT = ("numpy", "zarr", "pyarrow", "fsspec", "pydantic", "torch", "datagen-reader", "osvp")

MAKE_POCO_DATASET = """
import sys
sys.path.insert(0, {here!r})
from make_dataset import main
main({out!r}, refiner="poco", objects=("builtin:capsule",), rotations=1)
"""

TRAIN_WITHOUT_DATAGEN = """
import importlib.util, json, sys
from pathlib import Path
assert importlib.util.find_spec("datagen") is None, "datagen is importable in the light environment"
import storage
from osvp.train import TrainOptions, train
from osvp.planning import load_scorer
dataset = storage.open_dataset({url!r})
assert dataset.info.config.refiner == "poco" and dataset.info.config.poco_weights == "builtin"
out = Path({out!r})
train(TrainOptions(data={url!r}, out=out, epochs=1, batch_size=16, target="mincover"))
scorer = load_scorer(out / "best.pt")
print(json.dumps({{"config_hash": dataset.info.config_hash, "views": len(scorer.decodings)}}))
"""


def run(command: list[str], **kwargs: object) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(command, capture_output=True, text=True, check=False, **kwargs)  # type: ignore[call-overload]
    assert done.returncode == 0, f"{' '.join(command[:4])} ... failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done


@pytest.mark.slow
def test_trainer_install_is_light_and_trains_on_a_poco_dataset(tmp_path: Path) -> None:
    pytest.importorskip("datagen", reason="the POCO dataset of this test is made with datagen (pip install -e .)")
    dataset = tmp_path / "poco-dataset"
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    run([sys.executable, "-c", MAKE_POCO_DATASET.format(here=str(HERE), out=str(dataset))], env=env)
    recorded = json.loads((dataset / "dataset.json").read_text())["config_hash"]

    venv = tmp_path / "light"
    run([sys.executable, "-m", "venv", "--without-pip", str(venv)])
    python = venv / "bin" / "python"
    install = [sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-input"]
    # torch pinned first, as the README says: an unpinned one would pull a CUDA build.
    run([*install, "torch==2.13.0"], env=env)
    for project in ("reader", "osvp"):
        # pip builds in the project's folder: a module deleted since the last build must not ride along.
        shutil.rmtree(REPO / project / "build", ignore_errors=True)
    run([*install, str(REPO / "reader"), str(REPO / "osvp")], env=env)

    listed = run([sys.executable, "-m", "pip", "--python", str(python), "list", "--format", "json"], env=env)
    installed = {entry["name"].lower().replace("_", "-") for entry in json.loads(listed.stdout)}
    assert sorted(installed & set(GENERATOR_ONLY)) == []
    assert sorted(set(LIGHT) - installed) == []

    # Outside the checkout, so that nothing of it is importable from the working directory.
    work = tmp_path / "elsewhere"
    work.mkdir()
    script = TRAIN_WITHOUT_DATAGEN.format(url=str(dataset), out=str(tmp_path / "run"))
    done = run([str(python), "-c", script], cwd=work, env={**env, "PYTHONPATH": ""})
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["config_hash"] == recorded
    assert (tmp_path / "run" / "best.pt").is_file()
