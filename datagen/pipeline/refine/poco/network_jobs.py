"""The POCO network's work for one observation as a record that can travel, and who runs it.

A task prepares everything that needs its own state on its own CPU (the queried keys, which need its
depth buffers and bands; the input points drawn from its random stream) and hands the network a
`NetworkJob`: the three tensors of `inputs.network_tensors` as arrays and the torch generator's state
for the encoder's sampling. Running a job is then a pure function of (job, weights, device, neighbour
backend), so it may run in the task's process (`LocalNetwork`) or in one holder of the network per
device shared by every task on a node (`NetworkHost`, which the engine puts in a Ray actor): the same
probabilities either way, because one job at a time runs exactly `inputs.predict_probs`'s
computation. With ``encoder_batch`` > 1 a host runs the encoder on several jobs at once (what makes a
GPU pay); that moves latents by float rounding (~1e-7 measured on the CPU), so it is for accelerators,
whose results are already the CPU's only up to rounding, and its default is 1.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future
from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import torch
from threadpoolctl import threadpool_limits

from datagen.errors import ConfigError
from datagen.pipeline.refine.poco.inputs import (
    choose_inputs,
    decode_probs,
    exact_float32,
    network_tensors,
    place_on_device,
)
from datagen.pipeline.refine.poco.network import PocoModel
from datagen.pipeline.refine.poco.spatial import KnnBackend, pykdtree_available

JOB_QUERIES = 1_000_000
"""Queries a refiner sends to its network in one call at most (~30 MB of arrays): a task's cases
travel in a few calls, so memory stays bounded however many cases it has."""


@dataclass(frozen=True)
class NetworkJob:
    """One observation's network input, in the network frame, and the encoder's sampling state."""

    points: npt.NDArray[np.float32]
    """(3, n) chosen input points."""
    directions: npt.NDArray[np.float32]
    """(3, n) their unit directions to the camera."""
    queries: npt.NDArray[np.float32]
    """(3, M) the queried key centres."""
    generator_state: npt.NDArray[np.uint8]
    """`torch.Generator.get_state` of the CPU generator the encoder's sampling draws from."""
    weights_id: str = ""
    """sha256 of the weights the task's config names; a host holding other weights refuses the job."""

    @property
    def size(self) -> int:
        return int(self.queries.shape[1])

    def tensors(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return (
            torch.from_numpy(self.points)[None],
            torch.from_numpy(self.directions)[None],
            torch.from_numpy(self.queries)[None],
        )

    def generator(self) -> torch.Generator:
        generator = torch.Generator()
        generator.set_state(torch.from_numpy(self.generator_state.copy()))
        return generator


def network_job(
    inputs: npt.NDArray[Any],
    directions: npt.NDArray[Any],
    queries: npt.NDArray[Any],
    num_input_points: int,
    rng: np.random.Generator,
    generator: torch.Generator,
    weights_id: str = "",
) -> NetworkJob:
    """The job `inputs.predict_probs` runs for these inputs (metres): the input draw consumes ``rng``
    exactly as it does, and the generator's state is taken as it stands."""
    pick = choose_inputs(inputs.shape[0], num_input_points, rng)
    points, dirs, q = network_tensors(inputs[pick], directions[pick], queries)
    return NetworkJob(
        points=points[0].numpy(),
        directions=dirs[0].numpy(),
        queries=q[0].numpy(),
        generator_state=generator.get_state().numpy().copy(),
        weights_id=weights_id,
    )


def run_network_jobs(
    model: PocoModel,
    jobs: Sequence[NetworkJob],
    device: torch.device | str,
    knn_backend: KnnBackend = "auto",
    *,
    fast: bool = True,
    encoder_batch: int = 1,
) -> list[npt.NDArray[np.float32]]:
    """p(inside) of every job's queries, in order. One job at a time (``encoder_batch`` 1) is
    `inputs.predict_probs` bit for bit; more runs the encoder on that many jobs at once (the tables
    and the decoder stay per job)."""
    results: list[npt.NDArray[np.float32]] = [np.zeros(0, dtype=np.float32)] * len(jobs)
    pending = [i for i, job in enumerate(jobs) if job.size > 0]
    step = max(1, int(encoder_batch))
    with torch.inference_mode() if fast else torch.no_grad(), exact_float32(device):
        for start in range(0, len(pending), step):
            group = pending[start : start + step]
            placed = [
                place_on_device(model, *jobs[i].tensors(), jobs[i].generator(), device, knn_backend) for i in group
            ]
            latents = _encode(model, placed, fast)
            for i, (points, _, tables, q), latent in zip(group, placed, latents, strict=True):
                results[i] = decode_probs(model, latent, points, q, tables["proj_indices"], fast)
    return results


def _encode(
    model: PocoModel, placed: list[tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor], torch.Tensor]], fast: bool
) -> list[torch.Tensor]:
    """Each placed job's latents (1, L, n): one encoder call for the group."""
    if len(placed) == 1:
        points, features, tables, _ = placed[0]
        return [model.encode(points, features, tables, fast)]
    points = torch.cat([p for p, _, _, _ in placed])
    features = torch.cat([f for _, f, _, _ in placed])
    names = [name for name in placed[0][2] if name != "proj_indices"]
    tables = {name: torch.cat([t[name] for _, _, t, _ in placed]) for name in names}
    latents = model.encode(points, features, tables, fast)
    return list(latents.split(1))


class NetworkRunner(Protocol):
    """Runs a refiner's network jobs; the answer is the same whoever runs them."""

    def run(self, jobs: Sequence[NetworkJob]) -> list[npt.NDArray[np.float32]]: ...

    def steps(self) -> dict[str, tuple[float, float]]:
        """Step name -> (CPU, wall) seconds spent outside the caller's process so far ({} when none),
        for the task's step table."""
        ...


class LocalNetwork:
    """The network in the refiner's own process (every refiner's default)."""

    def __init__(
        self, model: PocoModel, device: torch.device | str, knn_backend: KnnBackend = "auto", *, fast: bool = True
    ) -> None:
        self.model = model
        self.device = device
        self.knn_backend = knn_backend
        self.fast = fast

    def run(self, jobs: Sequence[NetworkJob]) -> list[npt.NDArray[np.float32]]:
        return run_network_jobs(self.model, jobs, self.device, self.knn_backend, fast=self.fast)

    def steps(self) -> dict[str, tuple[float, float]]:
        return {}


class RemoteNetwork:
    """A task's `NetworkRunner` whose jobs a `NetworkHost` in another process runs (``call`` sends a
    list of jobs there and returns its `NetworkReply`: a Ray actor's method on the engine, a pipe in
    `benchmarks/generation/task_cost.py`). It keeps where the jobs' time went, for the task's step
    table: ``refiner_queue`` (wall seconds its calls waited behind other tasks' at the host) and
    ``refiner_host`` (the host's CPU and wall seconds for its jobs)."""

    def __init__(self, call: Callable[[list[NetworkJob]], NetworkReply]) -> None:
        self.call = call
        self.queued = 0.0
        self.cpu = 0.0
        self.wall = 0.0

    def run(self, jobs: Sequence[NetworkJob]) -> list[npt.NDArray[np.float32]]:
        reply = self.call(list(jobs))
        self.queued += reply.queued
        self.cpu += reply.cpu
        self.wall += reply.wall
        return reply.probabilities

    def steps(self) -> dict[str, tuple[float, float]]:
        return {"refiner_queue": (0.0, self.queued), "refiner_host": (self.cpu, self.wall)}


@dataclass(frozen=True)
class NetworkReply:
    """A host's answer to one call: the probabilities and where the call's time went there."""

    probabilities: list[npt.NDArray[np.float32]]
    queued: float
    """Wall seconds the call waited behind other calls before its batch started."""
    cpu: float
    """The host's CPU seconds for this call's jobs (its share of each batch, by queries)."""
    wall: float
    """Wall seconds of the batches this call's jobs were in, its share by queries."""


@dataclass
class _Call:
    jobs: Sequence[NetworkJob]
    future: Future[NetworkReply]
    arrived: float = field(default_factory=time.perf_counter)


class NetworkHost:
    """One holder of the network for every task of a node: callers in many threads (a Ray actor's
    concurrent calls) hand it jobs; one thread runs what has arrived, several calls at a time, so a
    device sees batches across tasks instead of each task's small ones. Each caller gets its own
    jobs' answers in order, exactly what `LocalNetwork` gives with ``encoder_batch`` 1.

    ``batch_queries`` bounds a batch (the calls taken together); ``linger`` is how long the runner
    waits for more calls once one has arrived (0: take what is there).
    """

    def __init__(
        self,
        model: PocoModel,
        weights_id: str,
        device: torch.device | str,
        knn_backend: KnnBackend = "auto",
        *,
        encoder_batch: int = 1,
        batch_queries: int = 4 * JOB_QUERIES,
        linger: float = 0.0,
    ) -> None:
        self.model = model.eval()
        self.weights_id = weights_id
        self.device = torch.device(device)
        self.knn_backend = knn_backend
        self.encoder_batch = max(1, int(encoder_batch))
        self.batch_queries = batch_queries
        self.linger = linger
        self.served = 0
        """Calls answered so far."""
        self.batches = 0
        self._calls: queue.Queue[_Call | None] = queue.Queue()
        self._runner = threading.Thread(target=self._serve, name="network-host", daemon=True)
        self._runner.start()

    def run(self, jobs: Sequence[NetworkJob]) -> NetworkReply:
        """The jobs' probabilities, once the host has run them (blocks the calling thread)."""
        for job in jobs:
            if job.weights_id and self.weights_id and job.weights_id != self.weights_id:
                raise ConfigError(
                    f"this node's refiner holds weights {self.weights_id[:12]}, the task's config names "
                    f"{job.weights_id[:12]}: install the same weights on every node"
                )
        call = _Call(jobs, Future())
        self._calls.put(call)
        return call.future.result()

    def close(self) -> None:
        self._calls.put(None)
        self._runner.join(timeout=10.0)

    def _serve(self) -> None:
        while True:
            first = self._calls.get()
            if first is None:
                return
            batch = [first, *self._more(first)]
            self._run_batch(batch)

    def _more(self, first: _Call) -> Iterator[_Call]:
        """Calls that have arrived (or arrive within ``linger``), up to ``batch_queries`` in all."""
        total = sum(job.size for job in first.jobs)
        deadline = time.perf_counter() + self.linger
        while total < self.batch_queries:
            wait = deadline - time.perf_counter()
            try:
                call = self._calls.get(timeout=wait) if wait > 0 else self._calls.get_nowait()
            except queue.Empty:
                return
            if call is None:  # close(): finish this batch, then stop
                self._calls.put(None)
                return
            total += sum(job.size for job in call.jobs)
            yield call

    def _run_batch(self, batch: list[_Call]) -> None:
        started, cpu = time.perf_counter(), time.process_time()
        jobs = [job for call in batch for job in call.jobs]
        try:
            with self._limits():
                probabilities = run_network_jobs(
                    self.model, jobs, self.device, self.knn_backend, encoder_batch=self.encoder_batch
                )
        except BaseException as error:  # every caller of the batch hears it
            for call in batch:
                call.future.set_exception(error)
            return
        wall, used = time.perf_counter() - started, time.process_time() - cpu
        total = max(1, sum(job.size for job in jobs))
        self.batches += 1
        at = 0
        for call in batch:
            share = sum(job.size for job in call.jobs) / total
            answers = probabilities[at : at + len(call.jobs)]
            at += len(call.jobs)
            self.served += 1
            call.future.set_result(
                NetworkReply(answers, queued=started - call.arrived, cpu=used * share, wall=wall * share)
            )

    def _limits(self) -> ExitStack:
        """pykdtree's OpenMP bounded to torch's thread count, as in a worker (`PocoRefiner.execution`)."""
        stack = ExitStack()
        if self.knn_backend == "pykdtree" or (self.knn_backend == "ordered" and pykdtree_available()):
            stack.enter_context(threadpool_limits(limits=torch.get_num_threads(), user_api="openmp"))
        return stack
