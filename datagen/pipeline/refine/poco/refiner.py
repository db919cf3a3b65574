"""The ``poco`` refiner (PIPELINE.md section 4): a POCO network classifies the unknown band keys.

For each observation O: the band keys of O minus keys(O) minus the keys some view saw empty are
queried (`inputs.query_keys`, exactly the training queries); R(O) = the queries whose p(inside)
exceeds ``poco_threshold``. The network input is the centres of keys(O), clean, in the training
frame (`inputs.normalise`), each with its unit direction to its camera for ``*_sv`` presets. What the
network sees lives in `datagen.pipeline.refine.poco.inputs`, shared with training; this module never
loads training code.

Randomness (the input subset/repeats when |keys(O)| differs from the preset's point count, the
quantized sampling of the encoder, and the optional fine-tuning draws) comes from the case's
REFINER_NOISE stream (PIPELINE.md section 9), so a call is a function of (O, seed, object, rotation,
mask, weights, config). On CPU it is deterministic for a fixed torch thread count.

Optional test-time fine-tuning (``finetune_steps`` > 0; AIR used 10, the default here is 0): a copy
of the network takes that many Adam steps (lr 1e-3) on the observation itself, with the observed key
centres labelled inside and the sensor-empty band keys labelled outside (AIR's rule), then classifies.
"""

from __future__ import annotations

import copy
import hashlib
from collections.abc import Sequence
from importlib import resources
from pathlib import Path

import numpy as np
import numpy.typing as npt
import torch

from datagen.pipeline.keys import key_centres, unpack_keys
from datagen.pipeline.random_streams import Purpose, stream
from datagen.pipeline.refine.base import RefineRequest
from datagen.pipeline.refine.poco.inputs import (
    choose_inputs,
    forward_logits,
    network_tensors,
    observation_inputs,
    predict_probs,
    query_keys,
)
from datagen.pipeline.refine.poco.network import PocoModel
from schemas.config import GenerationConfig

BUILTIN_WEIGHTS = Path(str(resources.files("datagen"))) / "data" / "poco_small.pt"
FINETUNE_QUERIES = 4096


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
    ) -> None:
        self.config = config
        self.model = model.eval()
        self.weights_id = weights_id
        self.threshold = float(threshold)
        self.finetune_steps = int(finetune_steps)
        self.device = torch.device(device)

    def refine(self, requests: Sequence[RefineRequest]) -> list[npt.NDArray[np.int64]]:
        return [self.refine_one(request) for request in requests]

    def probabilities(self, request: RefineRequest) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]:
        """The queried keys of the request and p(inside) of each."""
        config = self.config
        observation = request.observation
        if observation.keys.size == 0:
            return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.float32)
        _, queries, _ = query_keys(observation, config)
        if queries.size == 0:
            return queries, np.empty(0, dtype=np.float32)
        rng = stream(request.seed, request.object_id, request.rotation, Purpose.REFINER_NOISE, request.mask)
        generator = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
        inputs, directions = observation_inputs(observation, config.voxel_size, config.grid_offset)
        model = self.model
        if self.finetune_steps > 0:
            model = self._finetuned(request, inputs, directions, rng, generator)
        centres = key_centres(unpack_keys(queries), config.voxel_size, config.grid_offset)
        prob = predict_probs(model, inputs, directions, centres, rng, generator, self.device)
        return queries, prob

    def refine_one(self, request: RefineRequest) -> npt.NDArray[np.int64]:
        queries, prob = self.probabilities(request)
        return queries[prob > self.threshold]

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
        unknown, _, empty = query_keys(observation, config)
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
            logits = forward_logits(model, points, dirs, qt, generator, self.device)
            loss = torch.nn.functional.cross_entropy(logits, labels.to(self.device))
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        return model.eval()
