"""`schemas` and `storage` (every layer's face) import and read a dataset without the heavy pipeline
dependencies, and torch comes in only with `storage.torch`."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from support import storage as fx

BLOCKED = ("ray", "torch", "trimesh", "embreex", "highspy", "open3d")

BLOCKER = textwrap.dedent(
    """
    import importlib.abc
    import sys

    BLOCKED = set(sys.argv[1].split(","))


    class Blocker(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ImportError(f"blocked import of {name}")
            return None


    sys.meta_path.insert(0, Blocker())
    for name in list(sys.modules):  # nothing blocked may already be loaded (sitecustomize, .pth files)
        assert name.split(".")[0] not in BLOCKED, name
    """
)

READ_WITHOUT_PIPELINE = BLOCKER + textwrap.dedent(
    """
    import json

    import schemas, storage
    import storage.store, storage.samples, storage.shards, storage.dataset
    import storage.readers, storage.checks, storage.export
    from storage import open_dataset, validate

    for name in sys.argv[2].split(","):  # the blocker really blocks
        try:
            __import__(name)
        except ImportError:
            pass
        else:
            raise SystemExit(f"{name} was importable despite the blocker")

    ds = open_dataset(sys.argv[3])
    first, last = ds[0], ds[len(ds) - 1]
    train, val = ds.split(val=0.5, seed=0)
    report = {
        "len": len(ds),
        "first_id": first["sample_id"],
        "first_points": first["points"].shape[0],
        "last_keys": ds.keys(len(ds) - 1, "observed").tolist()[:3],
        "masks": list(ds.masks(0)),
        "split": [len(train), len(val)],
        "problems": validate(sys.argv[3], full=True),
        "loaded": sorted({m.split(".")[0] for m in sys.modules} & set(sys.argv[2].split(","))),
        "datagen_loaded": "datagen" in sys.modules,
    }
    print(json.dumps(report))
    """
)

TORCH_ONLY_WITH_STORAGE_TORCH = textwrap.dedent(
    """
    import json
    import sys

    import schemas, storage
    import storage.store, storage.samples, storage.shards, storage.dataset
    import storage.readers, storage.checks, storage.export
    after_storage = "torch" in sys.modules
    import storage.torch
    print(json.dumps({"after_storage": after_storage, "after_storage_torch": "torch" in sys.modules}))
    """
)


def run_python(code: str, *args: str, cwd: Path) -> str:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    env.pop("PYTHONPATH", None)
    done = subprocess.run(
        [sys.executable, "-c", code, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-4000:]
    return done.stdout.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> str:
    url = str(tmp_path_factory.mktemp("imports") / "ds")
    fx.build_dataset(url, finalise_index=True)
    return url


def test_schemas_and_storage_read_a_dataset_without_pipeline_dependencies(dataset: str, tmp_path: Path) -> None:
    from storage.readers import open_dataset

    report = json.loads(run_python(READ_WITHOUT_PIPELINE, ",".join(BLOCKED), ",".join(BLOCKED), dataset, cwd=tmp_path))
    expected = open_dataset(dataset)
    assert report["len"] == len(expected) == fx.total_samples()
    assert report["first_id"] == expected[0]["sample_id"]
    assert report["first_points"] == expected[0]["points"].shape[0]
    assert report["last_keys"] == expected.keys(len(expected) - 1, "observed").tolist()[:3]
    assert report["masks"] == list(expected.masks(0))
    assert sum(report["split"]) == len(expected) and min(report["split"]) > 0
    assert report["problems"] == []
    assert report["loaded"] == []
    assert report["datagen_loaded"] is False


def test_torch_is_imported_by_storage_torch_only(tmp_path: Path) -> None:
    if importlib.util.find_spec("torch") is None:
        pytest.skip("torch is not installed")
    report = json.loads(run_python(TORCH_ONLY_WITH_STORAGE_TORCH, cwd=tmp_path))
    assert report == {"after_storage": False, "after_storage_torch": True}
