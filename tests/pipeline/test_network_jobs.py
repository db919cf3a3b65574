"""The POCO network's work as travelling jobs (datagen/pipeline/refine/poco/network_jobs.py).

A refiner that sends its jobs elsewhere must answer exactly as one that runs them itself: one job at
a time is `predict_probs` bit for bit; a `NetworkHost` serving many callers at once gives each its
own answers, in order, the same bits; its encoder batches are the per-job answers up to float
rounding. Checked on a real task's single views and cases of a built-in, with the shipped weights.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from datagen.errors import ConfigError
from datagen.pipeline.imaging import Observation
from datagen.pipeline.keys import key_centres, unpack_keys
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.random_streams import Purpose, stream
from datagen.pipeline.refine import RefineRequest, make_refiner
from datagen.pipeline.refine.poco.inputs import observation_inputs, predict_probs, query_keys
from datagen.pipeline.refine.poco.network_jobs import (
    LocalNetwork,
    NetworkHost,
    NetworkJob,
    RemoteNetwork,
    network_job,
    run_network_jobs,
)
from datagen.pipeline.refine.poco.refiner import BUILTIN_WEIGHTS, PocoRefiner
from datagen.pipeline.scanning import scan_task
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig

CONFIG = GenerationConfig()
pytestmark = pytest.mark.skipif(not BUILTIN_WEIGHTS.is_file(), reason="no shipped POCO weights")


@pytest.fixture(scope="module")
def requests(tmp_path_factory) -> list[RefineRequest]:
    """Four single views and two cases of the built-in mug, rotation 1."""
    path = tmp_path_factory.mktemp("objects") / "objects.txt"
    path.write_text("builtin:mug\n")
    (spec,) = read_objects_file(path).objects
    scan = scan_task(prepare_object(spec, CONFIG), 1, CONFIG, build_view_space(CONFIG.view_space))
    singles = scan.observations
    observations = [singles[v] for v in (0, 9, 17, 26)]
    observations += [Observation.combine([singles[v] for v in case]) for case in ((0, 9), (9, 17, 26))]
    return [RefineRequest(o, CONFIG.seed, spec.object_id, 1) for o in observations]


@pytest.fixture(scope="module")
def refiner() -> PocoRefiner:
    made = make_refiner(CONFIG)
    assert isinstance(made, PocoRefiner)
    return made


def jobs_of(refiner: PocoRefiner, requests: list[RefineRequest]) -> list[NetworkJob]:
    """Each request's job as the refiner prepares it (the same draws as `PocoRefiner.refine`)."""
    jobs = []
    for request in requests:
        _, queries, _ = query_keys(request.observation, CONFIG)
        rng = stream(request.seed, request.object_id, request.rotation, Purpose.REFINER_NOISE, request.mask)
        generator = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
        inputs, directions = observation_inputs(request.observation, CONFIG.voxel_size, CONFIG.grid_offset)
        centres = key_centres(unpack_keys(queries), CONFIG.voxel_size, CONFIG.grid_offset)
        n = refiner.model.preset.num_input_points
        jobs.append(network_job(inputs, directions, centres, n, rng, generator, refiner.weights_id))
    return jobs


def test_one_job_is_predict_probs_bit_for_bit(refiner: PocoRefiner, requests: list[RefineRequest]) -> None:
    request = requests[4]
    _, queries, _ = query_keys(request.observation, CONFIG)
    inputs, directions = observation_inputs(request.observation, CONFIG.voxel_size, CONFIG.grid_offset)
    centres = key_centres(unpack_keys(queries), CONFIG.voxel_size, CONFIG.grid_offset)
    n = refiner.model.preset.num_input_points

    def draws() -> tuple[np.random.Generator, torch.Generator]:
        return np.random.default_rng(3), torch.Generator().manual_seed(3)

    direct = predict_probs(refiner.model, inputs, directions, centres, *draws(), "cpu", knn_backend="auto")
    job = network_job(inputs, directions, centres, n, *draws())
    (travelled,) = run_network_jobs(refiner.model, [job], "cpu", "auto")
    assert direct.size == queries.size > 0
    np.testing.assert_array_equal(travelled, direct)


def test_a_refiner_with_a_host_answers_as_one_without(refiner: PocoRefiner, requests: list[RefineRequest]) -> None:
    """The same R(O) whether the refiner runs its network itself or a `NetworkHost` runs it."""
    host = NetworkHost(refiner.model, refiner.weights_id, "cpu", refiner.knn_backend)
    try:
        remote = RemoteNetwork(host.run)
        hosted = PocoRefiner(CONFIG, refiner.model, refiner.weights_id, refiner.threshold, network=remote)
        alone = PocoRefiner(CONFIG, refiner.model, refiner.weights_id, refiner.threshold)
        assert isinstance(alone.network, LocalNetwork) and alone.network.steps() == {}
        for a, b in zip(alone.refine(requests), hosted.refine(requests), strict=True):
            np.testing.assert_array_equal(a, b)
        assert host.served == 1  # one call for all six requests
        steps = remote.steps()
        assert sorted(steps) == ["refiner_host", "refiner_queue"]
        assert steps["refiner_host"][0] > 0 and steps["refiner_host"][1] > 0  # the host's CPU and wall
    finally:
        host.close()


def test_a_host_serves_concurrent_callers_their_own_answers_in_order(
    refiner: PocoRefiner, requests: list[RefineRequest]
) -> None:
    jobs = jobs_of(refiner, requests)
    expected = LocalNetwork(refiner.model, "cpu", refiner.knn_backend).run(jobs)
    host = NetworkHost(refiner.model, refiner.weights_id, "cpu", refiner.knn_backend, linger=0.05)
    callers = [jobs[0:2], jobs[2:3], jobs[3:6], jobs[5:1:-1]]
    wanted = [expected[0:2], expected[2:3], expected[3:6], expected[5:1:-1]]
    answers: dict[int, list[np.ndarray]] = {}
    queued: dict[int, float] = {}

    def call(i: int) -> None:
        reply = host.run(callers[i])
        answers[i], queued[i] = reply.probabilities, reply.queued

    try:
        threads = [threading.Thread(target=call, args=(i,)) for i in range(len(callers))]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=120)
        assert sorted(answers) == list(range(len(callers)))
        for i, want in enumerate(wanted):
            assert len(answers[i]) == len(want)
            for got, exp in zip(answers[i], want, strict=True):
                np.testing.assert_array_equal(got, exp)
        assert host.served == len(callers)
        assert host.batches < len(callers)  # the lingering runner took calls together
        assert all(seconds >= 0 for seconds in queued.values())
    finally:
        host.close()


def test_encoder_batches_are_the_single_answers_up_to_rounding(
    refiner: PocoRefiner, requests: list[RefineRequest]
) -> None:
    jobs = jobs_of(refiner, requests)
    single = run_network_jobs(refiner.model, jobs, "cpu", refiner.knn_backend)
    batched = run_network_jobs(refiner.model, jobs, "cpu", refiner.knn_backend, encoder_batch=4)
    for a, b in zip(single, batched, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-4)
        assert np.mean((a > refiner.threshold) == (b > refiner.threshold)) > 0.999


def test_a_host_refuses_jobs_made_for_other_weights(refiner: PocoRefiner, requests: list[RefineRequest]) -> None:
    host = NetworkHost(refiner.model, "f" * 64, "cpu", refiner.knn_backend)
    try:
        with pytest.raises(ConfigError, match="install the same weights on every node"):
            host.run(jobs_of(refiner, requests[:1]))
    finally:
        host.close()


def test_a_batch_that_fails_fails_every_caller_in_it(refiner: PocoRefiner, requests: list[RefineRequest]) -> None:
    (job,) = jobs_of(refiner, requests[:1])
    broken = NetworkJob(job.points[:2], job.directions, job.queries, job.generator_state)  # 2 rows, not 3
    host = NetworkHost(refiner.model, refiner.weights_id, "cpu", refiner.knn_backend)
    try:
        with pytest.raises(Exception):  # noqa: B017 (torch's own shape error)
            host.run([broken])
        assert len(host.run([job]).probabilities[0]) == job.size  # the host goes on serving
    finally:
        host.close()


def test_a_job_travels_as_its_arrays(refiner: PocoRefiner, requests: list[RefineRequest]) -> None:
    import pickle

    (job,) = jobs_of(refiner, requests[:1])
    again = pickle.loads(pickle.dumps(job))
    np.testing.assert_array_equal(again.queries, job.queries)
    assert torch.equal(again.generator().get_state(), job.generator().get_state())
    arrays = job.points.nbytes + job.directions.nbytes + job.queries.nbytes + job.generator_state.nbytes
    assert len(pickle.dumps(job)) < arrays + 2048  # the arrays and little else travel
