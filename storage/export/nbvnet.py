"""``--layout nbvnet``: the case files MA-SCVP's generator writes for NBVNet, and the arrays its trainer loads.

Text, per case (their ``NBVNET_LongTailSample/<object>/rotate_<k>/``): ``grid_<c>.txt`` (as
``--layout mascvp``'s) and ``id_<c>.txt`` (the best next view). Arrays, per split:
``<split>/grids.npy`` (N, 32768) float32 and ``<split>/labels.npy`` (N,) int64, the two files
``Networks_pytorch/nbv-net-master/train.py`` opens in its working folder, plus ``points_in_sphere.txt``
(the 32 view positions, which it also opens) at the root (docs/authors-code.md section 7.4).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np

from storage.export.arrays import ARRAY_ROWS, ArrayFile, SplitArrays
from storage.export.base import Layout, Place, Run, Writer
from storage.export.grids import Grids, grid_facts, grid_line
from storage.export.options import NO_NEXT_VIEW, TEST, TRAIN
from storage.export.publish import write_text
from storage.export.text import cpp_text
from storage.readers.reader import Dataset, Sample
from storage.samples.occupancy_grid import GRID_CELLS

AUTHORS_CODE = (
    "psc0628/MA-SCVP @ 586509a, Dataset_generator/main.cpp (NBVNET_LongTailSample), "
    "Networks_pytorch/nbv-net-master/{train,classification_nbv}.py"
)
POSITIONS = "points_in_sphere.txt"
ARRAYS = (
    ArrayFile("grids", "{split}/grids.npy", np.float32, (GRID_CELLS,)),
    ArrayFile("labels", "{split}/labels.npy", np.int64, ()),
)


class NbvnetLayout(Layout):
    name = "nbvnet"
    reader = "MA-SCVP's generator layout for NBVNet and the NBVNet trainer"
    read_by = AUTHORS_CODE
    summary = "NBVNet's grid and id files, and the grids/labels arrays of its trainer"
    reserved = (TRAIN, TEST, ARRAY_ROWS, POSITIONS)
    skip_reasons: ClassVar[Mapping[str, str]] = {
        NO_NEXT_VIEW: "the case holds every view, so there is no class to learn; their generator would write -1, "
        "which their cross-entropy cannot take",
    }
    fields = ("view_state", "best_view")
    split_use = (
        "train/ holds the train_split objects' arrays, test/ the test_split ones; their train.py reads "
        "./grids.npy and ./labels.npy, trains on all of them and reports a validation loss on a random 20% "
        "(seed 42) that it also trains on"
    )

    def skipped(self, dataset: Dataset) -> list[str]:
        return [NO_NEXT_VIEW if best < 0 else "" for best in dataset.values("best_view", keep=False)]

    def start(self, run: Run) -> Writer:
        return _NbvnetWriter(run)

    def dataset_note(self, dataset: Dataset) -> str:
        return (
            "the class is the best next view: the largest visibility gain (keys of V_i the case has not "
            "seen) outside the case, the lowest index among equals, as their first-maximum loop picks it"
        )


class _NbvnetWriter(Writer):
    def __init__(self, run: Run) -> None:
        self.run = run
        self.grids = Grids(run.dataset)
        self.arrays = SplitArrays(run, ARRAYS)
        self.ties = 0
        ties = run.dataset.values("best_view_ties", keep=False)
        self._tied = ties > 1

    def write(self, place: Place, sample: Sample) -> None:
        target, c = self.run.target, place.case
        best = int(sample["best_view"])
        grid = self.grids.of(place.index, sample["view_state"])
        write_text(place.folder / f"grid_{c}.txt", cpp_text(grid), target)
        write_text(place.folder / f"id_{c}.txt", f"{best}\n", target)
        self.arrays.put(place, {"grids": grid.astype(np.float32), "labels": best})
        self.ties += bool(self._tied[place.index])

    def finish(self) -> None:
        positions = np.asarray(self.run.dataset.info.view_positions, dtype=np.float64)
        write_text(self.run.staging / POSITIONS, cpp_text(positions, columns=3), self.run.target)
        self.arrays.close()

    def lines(self) -> list[str]:
        return [
            grid_line("grid"),
            f"id: the best next view, one line; {self.ties} written samples share their best gain with another "
            "view outside the case (the lowest index is written, as theirs)",
            "case numbers: <c> of grid_<c> and id_<c> is the sample's row in its task's shard, the task's cases "
            "ordered by (size, mask); theirs is the case's line in their view_cases list",
            "arrays: <split>/grids.npy (N, 32768) float32 (the grid files' values) and <split>/labels.npy (N,) "
            f"int64 (the ids), one row per written sample in {ARRAY_ROWS}'s order (shard by shard); "
            f"{POSITIONS}: the 32 view positions, x y z in metres of the task frame (their train.py reads it "
            "and never uses it); the conversion from their text files is not in their repository, these "
            "dtypes and shapes are ours, chosen for what their NBVClassificationDatasetFull loads",
        ]

    def facts(self) -> dict[str, Any]:
        return {
            "grid": grid_facts(),
            "id": {
                "meaning": "best next view: largest view_gains outside the case, lowest index among equals",
                "tied_samples": self.ties,
            },
            "case_number": "the sample's row in its task's shard (cases ordered by size, then mask)",
            "arrays": self.arrays.facts(),
            "array_rows": ARRAY_ROWS,
            "positions": POSITIONS,
        }


NBVNET = NbvnetLayout()
