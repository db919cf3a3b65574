"""Refiner metrics against true occupancy (watertight meshes only).

For one single view O of a task: the domain D = band keys of O minus keys(O) (the unknown band;
sensor-empty keys stay in D and count as predicted empty by every refiner). Truth T = the keys of D
whose centre is inside the mesh. For a refiner's R(O) (a subset of D):

- precision |R & T| / |R|, recall |R & T| / |T|, IoU of the occupied class |R & T| / |R | T|;
- mIoU = mean of the occupied-class and empty-class IoU over D;
- hidden recall: among P_gt keys in D (hidden surface keys), the fraction in R(O) (so in P(O)).

Counts are summed over an object's views (micro-average); the mean row averages the objects.
Methods: the given refiners (``poco``, ``carve``, optionally ``poisson``) and ``oracle`` (R = T), all
on the same views.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import trimesh

from datagen.pipeline.keys import key_centres, unpack_keys
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.objects.spec import ObjectSpec
from datagen.pipeline.refine.base import Refiner, RefineRequest, band_keys
from datagen.pipeline.scanning import scan_task
from datagen.pipeline.thread_limits import single_threaded_blas
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig


@dataclass
class Counts:
    tp: int = 0
    fp: int = 0
    fn: int = 0
    tn: int = 0
    hidden: int = 0
    hidden_kept: int = 0
    domain: int = 0
    views: int = 0
    seconds: float = 0.0

    def add(self, predicted: npt.NDArray[np.bool_], truth: npt.NDArray[np.bool_], is_gt: npt.NDArray[np.bool_]) -> None:
        self.tp += int((predicted & truth).sum())
        self.fp += int((predicted & ~truth).sum())
        self.fn += int((~predicted & truth).sum())
        self.tn += int((~predicted & ~truth).sum())
        self.hidden += int(is_gt.sum())
        self.hidden_kept += int((predicted & is_gt).sum())
        self.domain += int(truth.size)
        self.views += 1

    def metrics(self) -> dict[str, float]:
        def ratio(a: int, b: int) -> float:
            return a / b if b else float("nan")

        iou1 = ratio(self.tp, self.tp + self.fp + self.fn)
        iou0 = ratio(self.tn, self.tn + self.fp + self.fn)
        return {
            "precision": ratio(self.tp, self.tp + self.fp),
            "recall": ratio(self.tp, self.tp + self.fn),
            "iou": iou1,
            "miou": (iou0 + iou1) / 2,
            "hidden_recall": ratio(self.hidden_kept, self.hidden),
            "band_per_view": ratio(self.domain, self.views),
            "seconds_per_view": self.seconds / self.views if self.views else float("nan"),
        }


@dataclass
class ObjectResult:
    name: str
    skipped: str = ""
    counts: dict[str, Counts] = field(default_factory=dict)


def evaluate_object(
    spec: ObjectSpec,
    config: GenerationConfig,
    refiners: Mapping[str, Refiner],
    views: Sequence[int] | None = None,
    every: int = 4,
    rotation: int = 0,
) -> ObjectResult:
    """Metrics of each refiner (and the oracle) over single views of task (object, rotation)."""
    with single_threaded_blas():
        prepared = prepare_object(spec, config)
        if not prepared.watertight:
            return ObjectResult(spec.name, skipped="open mesh (not watertight): inside/outside undefined")
        imaging = scan_task(prepared, rotation, config, build_view_space(config.view_space))
        mesh = trimesh.Trimesh(prepared.task_vertices(rotation, config.rotations), prepared.faces, process=False)
        chosen = list(views) if views is not None else list(range(0, len(imaging.observations), every))
        result = ObjectResult(spec.name, counts={name: Counts() for name in (*refiners, "oracle")})
        gt_keys = imaging.ground_truth.keys
        for view in chosen:
            observation = imaging.observations[view]
            if observation.keys.size == 0:
                continue
            band = band_keys(observation.keys, config.band_keys_sq)
            domain = np.setdiff1d(band, observation.keys, assume_unique=True)
            truth = np.asarray(mesh.contains(key_centres(unpack_keys(domain), config.voxel_size, config.grid_offset)))
            is_gt = np.isin(domain, gt_keys, assume_unique=True)
            request = RefineRequest(observation, config.seed, spec.object_id, rotation)
            for name, refiner in refiners.items():
                started = time.perf_counter()
                refined = refiner.refine([request])[0]
                result.counts[name].seconds += time.perf_counter() - started
                if not np.isin(refined, domain, assume_unique=True).all():
                    raise AssertionError(f"{name}: R(O) has keys outside the unknown band")
                result.counts[name].add(np.isin(domain, refined, assume_unique=True), truth, is_gt)
            result.counts["oracle"].add(truth, truth, is_gt)
    return result


def mean_metrics(results: Sequence[ObjectResult], method: str) -> dict[str, float]:
    rows = [r.counts[method].metrics() for r in results if not r.skipped and method in r.counts]
    if not rows:
        return {}
    means = {}
    for key in rows[0]:
        values = [row[key] for row in rows if not np.isnan(row[key])]
        means[key] = float(np.mean(values)) if values else float("nan")
    return means
