"""``--layout pcnbv``: the case files MA-SCVP's generator writes for PC-NBV, and the tensors its trainer loads.

Text, per case (their ``PCNBV_LongTailSample/<object>/rotate_<k>/``): ``cloud_<c>.txt`` (N points
"x y z" drawn from what the case's views saw), ``state_<c>.txt`` (32 lines 0/1), ``score_<c>.txt``
(32 lines: view i's visibility gain over every key some view sees). Tensors, per split, under
``dataset/`` as ``Networks_pytorch/PC-NBV_pytorch/train.py`` names them: accumulated clouds
(N, P, 3), ground-truth clouds (N, G, 3), view states (N, 32) and target values (N, 32), all float32
(docs/authors-code.md section 7.5). Their loader class (``dataset/dataset.py``'s ``ShapeNet3``) is
not released; what it must do with these files is recorded in the provenance.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from schemas.shard import GT_KEYS
from storage.export.arrays import ARRAY_ROWS, ArrayFile, SplitArrays
from storage.export.base import Layout, Place, Run, Writer
from storage.export.options import AUTHORS_VIEWS, NO_POINTS
from storage.export.publish import write_text
from storage.export.streams import draw, sample_rng, task_rng
from storage.export.text import bits32, cpp_text, state_text
from storage.readers.reader import Dataset, Sample

AUTHORS_CODE = (
    "psc0628/MA-SCVP @ 586509a, Dataset_generator/main.cpp (PCNBV_LongTailSample), "
    "Networks_pytorch/PC-NBV_pytorch/train.py"
)
FOLDER = "dataset"
INPUT_POINTS = 512
"""Their generator's RandomSample count and train.py's ``--num_input`` default."""
GT_POINTS = 16384
"""train.py's ``--num_gt`` default (PC-NBV's ShapeNet loader resamples every ground truth to it)."""


def _arrays(points: int, gt_points: int) -> tuple[ArrayFile, ...]:
    return (
        ArrayFile("cloud", FOLDER + "/accumulate_pointclouds_{split}.pt", np.float32, (points, 3)),
        ArrayFile("gt", FOLDER + "/gt_point_clouds_{split}.pt", np.float32, (gt_points, 3)),
        ArrayFile("state", FOLDER + "/view_statess_{split}.pt", np.float32, (AUTHORS_VIEWS,)),
        ArrayFile("target", FOLDER + "/target_values_{split}.pt", np.float32, (AUTHORS_VIEWS,)),
    )


class PcnbvLayout(Layout):
    name = "pcnbv"
    reader = "MA-SCVP's generator layout for PC-NBV and the PC-NBV trainer"
    read_by = AUTHORS_CODE
    summary = "PC-NBV's cloud, state and score files, and the four tensors of its trainer (--points 512)"
    reserved = (FOLDER, ARRAY_ROWS)
    points = INPUT_POINTS
    gt_points = GT_POINTS
    skip_reasons: ClassVar[Mapping[str, str]] = {
        NO_POINTS: "the case's views saw nothing, so there is no cloud to draw from"
    }
    fields = ("observed", "view_state")
    split_use = (
        "their train.py trains on the dataset/*_train.pt tensors (train_split objects) and validates on the "
        "dataset/*_test.pt ones (test_split objects), never trained on"
    )

    def skipped(self, dataset: Dataset) -> list[str]:
        return [NO_POINTS if not count else "" for count in dataset.values("num_observed", keep=False)]

    def start(self, run: Run) -> Writer:
        return _PcnbvWriter(run)

    def dataset_note(self, dataset: Dataset) -> str:
        return (
            "scores are view_gains / visible_size: the keys of V_i the case has not seen over every key some "
            "view sees (0 for the case's own views), their score[i] / full_num"
        )


class _PcnbvWriter(Writer):
    def __init__(self, run: Run) -> None:
        self.run = run
        self.points = int(run.options.num_points or INPUT_POINTS)
        self.gt_points = int(run.options.gt_points or GT_POINTS)
        self.arrays = SplitArrays(run, _arrays(self.points, self.gt_points))
        self.resampled = 0
        self.gt_resampled: set[str] = set()
        self.tasks = run.dataset.column("task_id").to_pylist()
        self.shards = run.dataset.column("shard").to_pylist()
        self._gt: tuple[str, npt.NDArray[np.float32]] | None = None

    def write(self, place: Place, sample: Sample) -> None:
        dataset, target, c, seed = self.run.dataset, self.run.target, place.case, self.run.options.seed
        view_state, observed = sample["view_state"], sample["observed"]
        chosen, replaced = draw(sample_rng(seed, place.sample_id), observed.shape[0], self.points)
        self.resampled += replaced
        cloud = observed[chosen]
        next_view = dataset.next_view(place.index)  # the raw gains and their denominator: the task's arrays
        score = next_view.view_gains.astype(np.float64) / next_view.visible_size
        write_text(place.folder / f"cloud_{c}.txt", cpp_text(cloud, columns=3), target)
        write_text(place.folder / f"state_{c}.txt", state_text(view_state), target)
        write_text(place.folder / f"score_{c}.txt", cpp_text(score), target)
        values = {"cloud": cloud, "gt": self._ground_truth(place.index), "state": bits32(view_state)}
        self.arrays.put(place, {**values, "target": score.astype(np.float32)})

    def _ground_truth(self, i: int) -> npt.NDArray[np.float32]:
        """The task's P_gt centres, ``gt_points`` of them, drawn once per task (samples arrive shard by
        shard, so only the current task's draw is kept)."""
        task = self.tasks[i]
        if self._gt is None or self._gt[0] != task:
            keys = self.run.dataset.shard(self.shards[i]).array(GT_KEYS)
            chosen, replaced = draw(task_rng(self.run.options.seed, task), keys.shape[0], self.gt_points)
            if replaced:
                self.gt_resampled.add(task)
            self._gt = (task, self.run.dataset.centres(keys[chosen]))
        return self._gt[1]

    def finish(self) -> None:
        self.arrays.close()

    def lines(self) -> list[str]:
        seed = self.run.options.seed
        voxel_mm = f"{self.run.dataset.info.config.voxel_size * 1000:g} mm"
        return [
            f"cloud: {self.points} points per case, drawn from the case's observed cloud (the {voxel_mm} keys "
            "its views see, keys(O_S), each once) without replacement, with replacement for the "
            f"{self.resampled} samples that have fewer (as PC-NBV's resample_pcd pads); seeded by (seed {seed}, "
            "sample id); theirs: pcl RandomSample of 512 from the concatenated clouds of the case's views (a "
            "point seen by k views is there k times; fewer than 512 stay fewer), printed as C++ prints a "
            "float, as here",
            "state and score: 32 lines 0/1, and 32 lines view_gains[i] / visible_size printed as C++ prints a "
            "double (6 significant digits), as theirs",
            f"ground truth: {self.gt_points} centres of the task's P_gt keys per sample (one draw per task, "
            f"seeded by (seed {seed}, task id); with replacement for {len(self.gt_resampled)} tasks with fewer "
            "keys); their generator writes no ground-truth cloud and their train.py moves it to the device "
            "without using it",
            "case numbers: <c> of cloud_<c>, state_<c> and score_<c> is the sample's row in its task's shard, "
            "the task's cases ordered by (size, mask); theirs is the case's line in their view_cases list",
            f"tensors: {FOLDER}/accumulate_pointclouds_<split>.pt (N, {self.points}, 3), "
            f"{FOLDER}/gt_point_clouds_<split>.pt (N, {self.gt_points}, 3), {FOLDER}/view_statess_<split>.pt "
            f"(N, 32), {FOLDER}/target_values_<split>.pt (N, 32), float32, one torch.save'd tensor each, one "
            f"row per written sample in {ARRAY_ROWS}'s order, the clouds' exact centres (the text rounds "
            "them); their loader class ShapeNet3 is not released: it must torch.load each file and return "
            "row i of the four, which is what these names, dtypes and shapes are ours for",
        ]

    def facts(self) -> dict[str, Any]:
        return {
            "cloud": {
                "per_case": self.points,
                "source": "observed: keys(O_S), the union of the case's views' visible keys, voxel centres",
                "sampling": "uniform without replacement; with replacement when the cloud has fewer points",
                "rng": "numpy default_rng(SeedSequence([seed, sha256(sample_id) first 8 bytes, little-endian]))",
                "seed": self.run.options.seed,
                "drawn_with_replacement": self.resampled,
                "authors": "pcl RandomSample(512) of the concatenated view clouds, duplicates kept",
            },
            "score": "view_gains / visible_size (storage NextView), float64 in text, float32 in the tensor",
            "ground_truth": {
                "per_sample": self.gt_points,
                "source": "the task's P_gt keys, voxel centres, one draw per task shared by its samples",
                "rng": "numpy default_rng(SeedSequence([seed, sha256(task_id) first 8 bytes, little-endian, 1]))",
                "tasks_drawn_with_replacement": len(self.gt_resampled),
            },
            "case_number": "the sample's row in its task's shard (cases ordered by size, then mask)",
            "arrays": self.arrays.facts(),
            "array_rows": ARRAY_ROWS,
        }


PCNBV = PcnbvLayout()
