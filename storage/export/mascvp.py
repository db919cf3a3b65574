"""``--layout mascvp``: the case files MA-SCVP's generator writes, and the arrays its trainer and SC-Net's load.

Text, per case (their ``MASCVP_LongTailSample/<object>/rotate_<k>/``): ``grid_<c>.txt`` (32,768
occupancy probabilities, one per line, x-major), ``state_<c>.txt`` (32 lines 0/1), ``ids_<c>.txt``
(the label's view ids, ascending). Arrays, per split: ``<split>/grid.npy`` (N, 32768) float32,
``<split>/vss.npy`` (N, 32) float32 view states, ``<split>/label.npy`` (N, 32) float32 multi-hot
labels: ``Networks_pytorch/ma_scvp``'s ``SCVPDataset`` loads ``GRID_PATH`` and the two paths made by
replacing "grid" in it (so OUT's path may not hold "grid"); SC-Net's ``VOXELDataset2`` loads a grid
and a label array of the same shapes (docs/authors-code.md section 7.3).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np

from storage.export.arrays import ARRAY_ROWS, ArrayFile, SplitArrays
from storage.export.base import Layout, Place, Run, Writer
from storage.export.grids import Grids, grid_facts, grid_line
from storage.export.options import AUTHORS_VIEWS, EMPTY_LABEL, TEST, TRAIN
from storage.export.publish import write_text
from storage.export.text import bits32, cpp_text, ids_text, state_text
from storage.readers.reader import Dataset, Sample
from storage.samples.occupancy_grid import GRID_CELLS

AUTHORS_CODE = (
    "psc0628/MA-SCVP @ 586509a, Dataset_generator/main.cpp (MASCVP_LongTailSample), "
    "Networks_pytorch/ma_scvp/{config,dataset,train}.py, Networks_pytorch/sc-net/{dataset,train}.py"
)
ARRAYS = (
    ArrayFile("grid", "{split}/grid.npy", np.float32, (GRID_CELLS,)),
    ArrayFile("vss", "{split}/vss.npy", np.float32, (AUTHORS_VIEWS,)),
    ArrayFile("label", "{split}/label.npy", np.float32, (AUTHORS_VIEWS,)),
)


class MascvpLayout(Layout):
    name = "mascvp"
    reader = "MA-SCVP's generator layout and the MA-SCVP and SC-Net trainers"
    read_by = AUTHORS_CODE
    summary = "MA-SCVP's grid, state and ids files, and the grid/vss/label arrays of its and SC-Net's trainers"
    path_word = "grid"
    reserved = (TRAIN, TEST, ARRAY_ROWS)
    skip_reasons: ClassVar[Mapping[str, str]] = {
        EMPTY_LABEL: "no view needed: both trainers' recall divides by the label size, and SC-Net's check after "
        "every epoch stops with ZeroDivisionError on one such sample; their generator writes none",
    }
    fields = ("view_state", "label")
    split_use = (
        "train/ holds the train_split objects' arrays, test/ the test_split ones; their ma_scvp train.py reads "
        "one set (config.GRID_PATH) and checks accuracy on a random 80% of it (seed 42) that it also trains "
        "on; SC-Net's holds out a random 20% of the set it reads"
    )

    def skipped(self, dataset: Dataset) -> list[str]:
        return [EMPTY_LABEL if not label else "" for label in dataset.values("label", keep=False)]

    def start(self, run: Run) -> Writer:
        return _MascvpWriter(run)

    def dataset_note(self, dataset: Dataset) -> str:
        tie_break = dataset.info.config.label_tie_break
        return (
            f"labels are exact minimum covers of P_full (alpha filter), the lexicographically smallest in the "
            f"{tie_break!r} view order; theirs are Gurobi's covers (10 s limit) of every voxel the case has not seen"
        )


class _MascvpWriter(Writer):
    def __init__(self, run: Run) -> None:
        self.run = run
        self.grids = Grids(run.dataset)
        self.arrays = SplitArrays(run, ARRAYS)

    def write(self, place: Place, sample: Sample) -> None:
        view_state, label = sample["view_state"], sample["label"]
        grid = self.grids.of(place.index, view_state)
        target, c = self.run.target, place.case
        write_text(place.folder / f"grid_{c}.txt", cpp_text(grid), target)
        write_text(place.folder / f"state_{c}.txt", state_text(view_state), target)
        write_text(place.folder / f"ids_{c}.txt", ids_text(label), target)
        self.arrays.put(place, {"grid": grid.astype(np.float32), "vss": bits32(view_state), "label": bits32(label)})

    def finish(self) -> None:
        self.arrays.close()

    def lines(self) -> list[str]:
        return [
            grid_line("grid"),
            "state and ids: 32 lines 0/1 (line v: view v is in the case) and the label's view ids, ascending, "
            "as theirs",
            "case numbers: <c> of grid_<c>, state_<c> and ids_<c> is the sample's row in its task's shard, the "
            "task's cases ordered by (size, mask); theirs is the case's line in their view_cases list",
            "arrays: <split>/grid.npy (N, 32768) float32 (the grid files' values), <split>/vss.npy (N, 32) "
            "float32 view states, <split>/label.npy (N, 32) float32 multi-hot labels, one row per written "
            f"sample in {ARRAY_ROWS}'s order (shard by shard); the conversion from their text files is not in "
            "their repository, these names, dtypes and shapes are ours, chosen for what their SCVPDataset and "
            "SC-Net's VOXELDataset2 load",
        ]

    def facts(self) -> dict[str, Any]:
        return {
            "grid": grid_facts(),
            "case_number": "the sample's row in its task's shard (cases ordered by size, then mask)",
            "arrays": self.arrays.facts(),
            "array_rows": ARRAY_ROWS,
        }


MASCVP = MascvpLayout()
