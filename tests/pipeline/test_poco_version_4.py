"""POCO version 4 (issue 50): the fast_sv network trained on real scans too, shipped as
``datagen/data/poco_fast.pt``.

The shipped file is the one its results were measured with (sha256 pinned here, in
studies/refiner/RESULTS.md and the model card); ``poco_version = 4`` alone loads it as the ``fast_sv``
preset at its tuned threshold; it refines a view deterministically on the CPU, inside the unknown band
and far better than chance against the true inside of the mesh; and a dataset made at an earlier
version keeps its version when a job resumes it after the default moved on.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

torch = pytest.importorskip("torch")

import trimesh  # noqa: E402
from support.engine import planned_tasks, queued_job  # noqa: E402

from datagen import api  # noqa: E402
from datagen.engine.worker import execute_task  # noqa: E402
from datagen.pipeline.keys import key_centres, unpack_keys  # noqa: E402
from datagen.pipeline.objects.prepare import prepare_object  # noqa: E402
from datagen.pipeline.objects.spec import BUILTIN_PREFIX  # noqa: E402
from datagen.pipeline.refine import make_refiner  # noqa: E402
from datagen.pipeline.refine.base import RefineRequest, band_keys  # noqa: E402
from datagen.pipeline.scanning import scan_task  # noqa: E402
from datagen.pipeline.viewspace import build_view_space  # noqa: E402
from datagen.settings import RunSettings  # noqa: E402
from datagen.training.poco_samples import sized_spec  # noqa: E402
from schemas import config as config_module  # noqa: E402
from schemas.config import GenerationConfig, builtin_poco_weights  # noqa: E402
from schemas.jobs import JobSpec  # noqa: E402
from storage import open_location, read_commit  # noqa: E402

SHA256 = "2fc73078907398e38e8ab27df268ff497613997e09e85375e6b6e7fc32795b54"
VERSION_2_SHA256 = "d88c55e35e82"
"""The first 12 hex digits of the shipped version 1-3 weights (poco_small.pt), as gpu-check.md records."""

pytestmark = pytest.mark.skipif(not builtin_poco_weights(4).is_file(), reason="no shipped POCO weights")


def test_version_4s_weights_are_the_measured_file() -> None:
    assert hashlib.sha256(builtin_poco_weights(4).read_bytes()).hexdigest() == SHA256


def test_version_4_refines_a_view_deterministically_with_its_own_network() -> None:
    config = GenerationConfig(poco_version=4)
    payload = torch.load(builtin_poco_weights(4), weights_only=True)
    assert json.loads(payload["extra"])["threshold"] == config.poco_threshold == 0.375  # export's tuned one
    refiner = make_refiner(config)
    assert refiner.weights_id == SHA256 and refiner.knn_backend == "pykdtree"
    assert refiner.model.preset.name == "fast_sv" and refiner.model.preset.decoder_k == 16
    assert refiner.model.preset.num_input_points == 1500
    spec = sized_spec("capsule", BUILTIN_PREFIX + "capsule", None, 0.08)
    prepared = prepare_object(spec, config)
    imaging = scan_task(prepared, 0, config, build_view_space(config.view_space))
    observation = imaging.observations[5]
    request = RefineRequest(observation, config.seed, spec.object_id, 0)
    first = refiner.refine([request])[0]
    np.testing.assert_array_equal(first, refiner.refine([request])[0])
    np.testing.assert_array_equal(first, make_refiner(config).refine([request])[0])  # a fresh refiner too
    band = band_keys(observation.keys, config.band_keys_sq)
    domain = np.setdiff1d(band, observation.keys, assume_unique=True)
    assert first.size and np.isin(first, domain).all()
    mesh = trimesh.Trimesh(prepared.task_vertices(0, config.rotations), prepared.faces, process=False)
    truth = mesh.contains(key_centres(unpack_keys(domain), config.voxel_size, config.grid_offset))
    precision = truth[np.isin(domain, first)].mean()
    assert precision > 2 * truth.mean() and precision > 0.8  # far better than keeping keys at random
    version_2 = make_refiner(GenerationConfig(poco_version=2)).refine([request])[0]
    assert not np.array_equal(first, version_2)  # another network, another R(O)


def test_a_dataset_keeps_its_poco_version_when_resumed_after_the_default_moved_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A job queued at version 2 (its config named no version), then the default becomes version 4: the
    ledgered job still says version 2 and version 2's network, and its task is refined and committed
    with version 2's weights into the dataset made at version 2, while a new config takes version 4."""
    queued = queued_job(tmp_path, "rotations = 1\n")
    home, job, made = queued.home, queued.job, queued.made
    assert made.config.poco_version == 2

    monkeypatch.setattr(config_module, "LATEST_POCO_VERSION", 4)
    assert (GenerationConfig().poco_version, GenerationConfig().poco_preset) == (4, "fast_sv")
    spec = JobSpec.model_validate(api.status(job.job_id, RunSettings(home=home))[0].spec)  # as resume reads it
    assert (spec.config.poco_version, spec.config.poco_preset, spec.config.poco_threshold) == (2, "small_sv", 0.65)
    assert spec.config.config_hash() == made.config_hash
    (task,) = planned_tasks(home, job.job_id)
    outcome = execute_task(task, spec.config, job.out, "a1-test", config_hash=made.config_hash)
    assert outcome.ok, outcome.message
    record = read_commit(open_location(job.out), task.task_id)
    assert record is not None and record.num_samples > 0
    index = pq.read_table(Path(job.out) / record.index_fragment)
    (weights_id,) = set(index.column("weights_id").to_pylist())
    assert weights_id == hashlib.sha256(builtin_poco_weights(2).read_bytes()).hexdigest()
    assert weights_id.startswith(VERSION_2_SHA256)
