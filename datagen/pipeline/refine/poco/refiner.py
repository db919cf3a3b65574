"""The ``poco`` refiner (docs/pipeline.md section 4): a POCO network classifies the unknown band keys.

For each observation O: the band keys of O minus keys(O) minus the keys some view saw empty are
queried (`inputs.query_keys`, exactly the training queries); R(O) = the queries whose p(inside)
exceeds ``poco_threshold``. The network input is the centres of keys(O), clean, in the training
frame (`inputs.normalise`), each with its unit direction to its camera for ``*_sv`` presets. What the
network sees lives in `datagen.pipeline.refine.poco.inputs`, shared with training; this module never
loads training code.

Randomness (the input subset/repeats when |keys(O)| differs from the preset's point count, the
quantized sampling of the encoder, and the optional fine-tuning draws) comes from the case's
REFINER_NOISE stream (docs/pipeline.md section 9), so a call is a function of (O, seed, object, rotation,
mask, weights, config). On CPU it is deterministic for a fixed torch thread count.

Speed (issue 24): the refiner keeps the depth buffers and the bands of the views it has seen
(`freespace.DepthBuffers`, `base.ViewBands`: a task's cases reuse its single views) and runs the
network through its inference path (`inputs.predict_probs` with ``fast=True``: cache-sized decoder
sub-chunks, in-place updates, and in the encoder a vectorised neighbour norm, amax, batch_norm for
one sample's instance norm: see `PocoModel.encode`). Every one of these gives bit-identical
probabilities, so the refiner's outputs, and the dataset's identity, are those of the original
execution, which ``fast=False`` still runs (benchmarks/generation/refine_speed.py,
tests/pipeline/test_refine_speed.py).

Versions (``GenerationConfig.poco_version``, part of the config hash): 1 is the computation above with
scipy's cKDTree building every neighbour table (all datasets made before versions existed); 2 builds
the decoder's table (each query's K nearest inputs, the largest search) with pykdtree instead
(`KNN_BACKENDS`): ~13 % less refinement CPU on the 2-core machine. Both searches are exact, but ~80 %
of queries have input points at exactly equal distances (key centres on a grid) and each search
breaks such ties its own way, 8-15 % of queries at the K-th neighbour; version 2 flips ~0.8 % of the
keys of R(O) (measured on the built-in mug). The encoder's tables stay cKDTree's: their ties move
every latent, and pykdtree there would flip ~7 % for another 2 % of CPU. Version 3 gives every table
one defined answer (nearest first, equal distances by index, `spatial.knn_ordered`) and searches on
the refiner's device: a k-d tree's candidates ordered exactly on the CPU, every distance on a GPU, the
same tables both ways, so a GPU run's R(O) is the CPU's up to the network's own float rounding.
Version 4 keeps version 2's search and changes the network (`schemas.config.POCO_VERSIONS`): the
``fast_sv`` preset (decoder K 16, 1,500 encoder points) with weights trained on real scans as well
(``datagen/data/poco_fast.pt``, threshold 0.375), about half version 2's refinement CPU; version 3's
search would cost it 1.35x again on the CPU, so a GPU run of version 4 is not the CPU's bit for bit.

Optional test-time fine-tuning (``finetune_steps`` > 0; AIR used 10, the default here is 0): a copy
of the network takes that many Adam steps (lr 1e-3) on the observation itself, with the observed key
centres labelled inside and the sensor-empty band keys labelled outside (AIR's rule), then classifies.
"""

from __future__ import annotations

import copy
import hashlib
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import numpy.typing as npt
import torch
from threadpoolctl import threadpool_limits

from datagen.errors import ConfigError
from datagen.pipeline.keys import key_centres, unpack_keys
from datagen.pipeline.random_streams import Purpose, stream
from datagen.pipeline.refine.base import RefineRequest, ViewBands
from datagen.pipeline.refine.freespace import DepthBuffers
from datagen.pipeline.refine.poco.inputs import (
    choose_inputs,
    forward_logits,
    network_tensors,
    observation_inputs,
    query_keys,
)
from datagen.pipeline.refine.poco.network import PocoModel
from datagen.pipeline.refine.poco.network_jobs import (
    JOB_QUERIES,
    LocalNetwork,
    NetworkJob,
    NetworkRunner,
    network_job,
    run_network_jobs,
)
from datagen.pipeline.refine.poco.spatial import KnnBackend, pykdtree_available
from schemas.config import GenerationConfig

BUILTIN_WEIGHTS = Path(str(resources.files("datagen"))) / "data" / "poco_small.pt"
FINETUNE_QUERIES = 4096
KNN_BACKENDS: dict[int, KnnBackend] = {1: "auto", 2: "pykdtree", 3: "ordered", 4: "pykdtree"}
"""The neighbour search of each ``poco_version``: versions 1, 2 and 4 name the decoder table's ("auto"
is scipy's cKDTree; the encoder's are cKDTree's, every table built on the CPU); version 3's "ordered"
is every table's, on the refiner's device (`spatial.knn_ordered`). What else a version brings (its
weights, preset and threshold) is `schemas.config.POCO_VERSIONS`'s."""


def weights_sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


class PocoRefiner:
    name = "poco"

    def __init__(
        self,
        config: GenerationConfig,
        model: PocoModel,
        weights_id: str,
        threshold: float,
        finetune_steps: int = 0,
        device: str | torch.device = "cpu",
        *,
        fast: bool = True,
        network: NetworkRunner | None = None,
    ) -> None:
        self.config = config
        self.model = model.eval()
        self.weights_id = weights_id
        self.threshold = float(threshold)
        self.finetune_steps = int(finetune_steps)
        self.device = torch.device(device)
        self.knn_backend = KNN_BACKENDS[config.poco_version]
        if self.knn_backend == "pykdtree" and not pykdtree_available():
            raise ConfigError(
                f"poco_version = {config.poco_version} builds its neighbour tables with pykdtree, which is not "
                "installed: pip install 'pykdtree>=1.4,<1.5' (or use poco_version = 1)"
            )
        self.fast = fast
        """False: the original execution (no buffer reuse, `PocoModel.decode` in 8192-query chunks,
        the encoder's original operations: `PocoModel.encode`); the same outputs, for benchmarks and the
        tests that check so. A property of this refiner: every call it makes passes it on."""
        self.depth_buffers: DepthBuffers | None = DepthBuffers() if fast else None
        self.view_bands: ViewBands | None = ViewBands(config.band_keys_sq) if fast else None
        self.network: NetworkRunner = network or LocalNetwork(self.model, self.device, self.knn_backend, fast=fast)
        """Who runs the network jobs: this process (`LocalNetwork`), or a node's shared host (the
        engine's `datagen.engine.refiner_host`); the same probabilities either way."""
        self._inside = False

    @contextmanager
    def execution(self) -> Iterator[None]:
        """For pykdtree, OpenMP bounded to torch's thread count (one per worker), for the calls inside;
        `refine` and `probabilities` enter it themselves, and a caller of many `probabilities` may enter
        it once around them (threadpoolctl costs ~1 ms)."""
        if self._inside:
            yield
            return
        with ExitStack() as stack:
            if self.knn_backend == "pykdtree" or (self.knn_backend == "ordered" and pykdtree_available()):
                stack.enter_context(threadpool_limits(limits=torch.get_num_threads(), user_api="openmp"))
            self._inside = True
            try:
                yield
            finally:
                self._inside = False

    def refine(self, requests: Sequence[RefineRequest]) -> list[npt.NDArray[np.int64]]:
        """R(O) of each request: every request's network job is prepared here, then the jobs go to
        `network` together (in calls of at most `network_jobs.JOB_QUERIES` queries)."""
        out: list[npt.NDArray[np.int64]] = []
        with self.execution():
            batch: list[_Prepared] = []
            queued = 0
            for request in requests:
                batch.append(self._prepared(request))
                queued += batch[-1].queries.size
                if queued >= JOB_QUERIES:
                    out.extend(queries[prob > self.threshold] for queries, prob in self._answered(batch))
                    batch, queued = [], 0
            out.extend(queries[prob > self.threshold] for queries, prob in self._answered(batch))
        return out

    def probabilities(self, request: RefineRequest) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]:
        """The queried keys of the request and p(inside) of each."""
        with self.execution():
            return self._answered([self._prepared(request)])[0]

    def _answered(self, batch: Sequence[_Prepared]) -> list[tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]]:
        """Each prepared request's queries and their probabilities: the jobs not yet answered go to
        `network` in one call."""
        sent = [prepared.job for prepared in batch if prepared.job is not None and prepared.answer is None]
        answers = iter(self.network.run(sent) if sent else [])
        out = []
        for prepared in batch:
            if prepared.answer is not None:
                prob = prepared.answer
            elif prepared.job is None:
                prob = np.empty(0, dtype=np.float32)
            else:
                prob = next(answers)
            out.append((prepared.queries, prob))
        return out

    def _prepared(self, request: RefineRequest) -> _Prepared:
        """The request's queried keys and the network job that classifies them (none without queries)."""
        config = self.config
        observation = request.observation
        if observation.keys.size == 0:
            return _Prepared(np.empty(0, dtype=np.int64))
        _, queries, _ = query_keys(observation, config, self.depth_buffers, self.view_bands)
        if queries.size == 0:
            return _Prepared(queries)
        rng = stream(request.seed, request.object_id, request.rotation, Purpose.REFINER_NOISE, request.mask)
        generator = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
        inputs, directions = observation_inputs(observation, config.voxel_size, config.grid_offset)
        centres = key_centres(unpack_keys(queries), config.voxel_size, config.grid_offset)
        if self.finetune_steps > 0:  # a network of its own: run here, on this refiner's device
            model = self._finetuned(request, inputs, directions, rng, generator)
            job = network_job(inputs, directions, centres, model.preset.num_input_points, rng, generator)
            answer = run_network_jobs(model, [job], self.device, self.knn_backend, fast=self.fast)[0]
            return _Prepared(queries, job, answer)
        n = self.model.preset.num_input_points
        return _Prepared(queries, network_job(inputs, directions, centres, n, rng, generator, self.weights_id))

    def _finetuned(
        self,
        request: RefineRequest,
        inputs: npt.NDArray[np.float64],
        directions: npt.NDArray[np.float64],
        rng: np.random.Generator,
        generator: torch.Generator,
    ) -> PocoModel:
        config = self.config
        observation = request.observation
        unknown, _, empty = query_keys(observation, config, self.depth_buffers, self.view_bands)
        negatives = key_centres(unpack_keys(unknown[empty]), config.voxel_size, config.grid_offset)
        model = copy.deepcopy(self.model).train()
        optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
        n = model.preset.num_input_points
        for _ in range(self.finetune_steps):
            pick = choose_inputs(inputs.shape[0], n, rng)
            half = FINETUNE_QUERIES // 2
            pos = inputs[rng.integers(0, inputs.shape[0], size=half)]
            neg = negatives[rng.integers(0, negatives.shape[0], size=half)] if negatives.size else pos[:0]
            q = np.concatenate([pos, neg])
            labels = torch.from_numpy(np.concatenate([np.ones(len(pos)), np.zeros(len(neg))]).astype(np.int64))[None]
            points, dirs, qt = network_tensors(inputs[pick], directions[pick], q)
            logits = forward_logits(model, points, dirs, qt, generator, self.device, self.knn_backend, self.fast)
            loss = torch.nn.functional.cross_entropy(logits, labels.to(self.device))
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        return model.eval()


@dataclass(frozen=True)
class _Prepared:
    """A request ready for the network: its queried keys, their job, and the answer when a fine-tuned
    copy of the network already gave it."""

    queries: npt.NDArray[np.int64]
    job: NetworkJob | None = None
    answer: npt.NDArray[np.float32] | None = None
