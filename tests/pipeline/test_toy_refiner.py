"""A refiner added from this test module alone (issue 51): one `RefinerKind`, no file of ours touched.
The config takes it by name, a task refines with it (its R(O) is what the samples hold beyond what was
seen), the dataset card and `datagen evaluate --help` list it; and the same refiner installed as a
package (an entry point of ``datagen.refiners``) reaches the Ray workers of `datagen submit`.

The toy refiner ``fill``: R(O) is every key of O's band that O does not hold (space carving without the
carving: what the ``carve`` refiner keeps before any view empties a key).
"""

from __future__ import annotations

import json
import subprocess
import textwrap
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from pydantic import ValidationError
from support.engine import datagen_command, subprocess_env, write_config, write_objects
from support.plugins import forget_plugins, install_distribution

from datagen.cli.main import app
from datagen.engine.driver import dataset_info
from datagen.engine.job_plan import object_ref
from datagen.engine.worker import execute_task
from datagen.pipeline.keys import points_to_packed
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.refine.base import RefineRequest, band_keys
from datagen.pipeline.refine.factory import make_refiner
from schemas.config import GenerationConfig
from schemas.jobs import TaskSpec
from schemas.refiners import REFINERS, RefinerKind, register_refiner
from storage import finalise, init_dataset, open_dataset, open_location, validate

NAME = "fill"
SMALL = {"rotations": 1, "voxel_size": 0.004, "alpha": 3}
OBJECTS = ("builtin:capsule", "builtin:cone")


class FillRefiner:
    """R(O): the band of O's keys, less O."""

    name = NAME
    weights_id = ""

    def __init__(self, config: GenerationConfig) -> None:
        self.radius_sq = config.band_keys_sq

    def refine(self, requests: Sequence[RefineRequest]) -> list[npt.NDArray[np.int64]]:
        return [
            np.setdiff1d(band_keys(r.observation.keys, self.radius_sq), r.observation.keys, assume_unique=True)
            for r in requests
        ]


def build_fill(config: GenerationConfig, device: str, network: object = None) -> FillRefiner:
    return FillRefiner(config)


@pytest.fixture(scope="module", autouse=True)
def toy_refiner() -> Iterator[None]:
    register_refiner(RefinerKind(NAME, build_fill, "the whole band of what was seen"))
    yield
    REFINERS.unregister(NAME)


def make_dataset(config: GenerationConfig, out: Path, objects: Path) -> str:
    """The objects' tasks run one by one in this process, as a worker runs them."""
    location = open_location(str(out))
    info = init_dataset(location, dataset_info(config))
    for spec in read_objects_file(objects).objects:
        task = TaskSpec(task_id=spec.task_id(0), object=object_ref(spec), rotation=0)
        outcome = execute_task(task, config, str(out), f"toy-{time.monotonic_ns()}", config_hash=info.config_hash)
        assert outcome.ok, outcome.message
    finalise(location)
    return str(out)


def test_the_config_takes_the_toy_by_name_and_refuses_an_unknown_one() -> None:
    config = GenerationConfig(refiner=NAME, **SMALL)
    assert config.refiner_kind is REFINERS[NAME]
    assert isinstance(make_refiner(config), FillRefiner)
    with pytest.raises(
        ValidationError, match=r"unknown refiner 'magic'; choose one of none, carve, poisson, poco, fill"
    ):
        GenerationConfig(refiner="magic")
    # a refiner that reads no later field keeps every other refiner's identity rules
    assert "poco_version" not in config.canonical_dict() and config.config_hash() != GenerationConfig().config_hash()


def test_a_dataset_refined_by_the_toy_holds_its_band_and_validates(tmp_path: Path, runner) -> None:  # type: ignore[no-untyped-def]
    objects = write_objects(tmp_path / "objects.txt", OBJECTS)
    toy = GenerationConfig(refiner=NAME, **SMALL)
    plain = GenerationConfig(refiner="none", **SMALL)
    refined = open_dataset(make_dataset(toy, tmp_path / "fill", objects))
    seen = open_dataset(make_dataset(plain, tmp_path / "none", objects))
    assert validate(str(tmp_path / "fill"), full=True) == []
    assert refined.info.config.refiner == NAME and len(refined) > 0
    by_id = {seen[i]["sample_id"]: seen[i] for i in range(len(seen))}
    assert sorted(by_id) == sorted(refined.values("sample_id"))  # the input cases do not depend on the refiner
    for i in range(len(refined)):
        sample = refined[i]
        other = by_id[sample["sample_id"]]
        keys = np.sort(points_to_packed(sample["points"], toy.voxel_size, toy.grid_offset))
        observed = np.sort(points_to_packed(other["points"], plain.voxel_size, plain.grid_offset))
        assert np.array_equal(keys, band_keys(observed, toy.band_keys_sq))  # P(O) = O and its whole band
        seen_keys = np.sort(points_to_packed(sample["observed"], toy.voxel_size, toy.grid_offset))
        assert np.array_equal(seen_keys, observed)  # what was seen: the none refiner's whole cloud
    card = runner.invoke(app, ["shards", "card", str(tmp_path / "fill"), "--no-fixed", "--out", "-"])
    assert card.exit_code == 0 and f"- refiner: {NAME}; band {toy.band} m" in card.stdout


def test_evaluate_lists_the_toy_refiner(runner, monkeypatch: pytest.MonkeyPatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setenv("COLUMNS", "4000")
    result = runner.invoke(app, ["evaluate", "--help"])
    assert result.exit_code == 0
    assert f"poco or {NAME} (default: the config's)" in " ".join(result.stdout.replace("│", " ").split())


TOY_PACKAGE = '''
"""A third-party refiner: the whole band of what was seen, recording which process built it."""
import json
import os

import numpy as np

from schemas.refiners import RefinerKind


class FillRefiner:
    name = "fill_plugin"
    weights_id = ""

    def __init__(self, radius_sq):
        self.radius_sq = radius_sq

    def refine(self, requests):
        from datagen.pipeline.refine.base import band_keys

        return [
            np.setdiff1d(band_keys(r.observation.keys, self.radius_sq), r.observation.keys, assume_unique=True)
            for r in requests
        ]


def build(config, device, network=None):
    import ray

    with open(os.environ["TOY_REFINER_LOG"], "a") as log:
        log.write(json.dumps({"pid": os.getpid(), "task": ray.get_runtime_context().get_task_id()}) + "\\n")
    return FillRefiner(config.band_keys_sq)


KIND = RefinerKind("fill_plugin", build, "the whole band of what was seen (a plug-in)")
'''


@pytest.mark.ray
@pytest.mark.slow
def test_an_installed_refiner_reaches_the_ray_workers(tmp_path: Path) -> None:
    site = tmp_path / "site"
    site.mkdir()
    install_distribution(site, "toy-refiner", "toy_refiner", textwrap.dedent(TOY_PACKAGE), "datagen.refiners",
                         "fill_plugin", "toy_refiner:KIND")  # fmt: skip
    objects = write_objects(tmp_path / "objects.txt", OBJECTS)
    config = write_config(tmp_path / "plugin.toml", 1, refiner="fill_plugin", voxel_size=0.004, alpha=3)
    log = tmp_path / "built.jsonl"
    env = subprocess_env() | {"PYTHONPATH": str(site), "TOY_REFINER_LOG": str(log)}
    out = tmp_path / "plugin-data"
    args = ["submit", "--objects", str(objects), "--config", str(config), "--out", str(out)]
    done = subprocess.run(
        datagen_command(*args, "--home", str(tmp_path / "home"), "--workers", "2"),
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    forget_plugins()
    assert done.returncode == 0, done.stdout + done.stderr
    builds = [json.loads(line) for line in log.read_text().splitlines()]
    assert builds and all(build["task"] is not None for build in builds)  # built inside Ray tasks
    plugin = open_dataset(str(out))
    assert plugin.info.config.refiner == "fill_plugin"
    # the same samples as the toy registered here, whose name differs (so does the config hash)
    here = open_dataset(make_dataset(GenerationConfig(refiner=NAME, **SMALL), tmp_path / "here", objects))
    assert sorted(plugin.values("sample_id")) == sorted(here.values("sample_id"))
    ours = {here[i]["sample_id"]: here[i]["points"] for i in range(len(here))}
    for i in range(len(plugin)):
        sample = plugin[i]
        assert np.array_equal(sample["points"], ours[sample["sample_id"]])
