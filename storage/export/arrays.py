"""The arrays the authors' trainers load, one file per split and kind, filled row by row.

Their generator writes text files per case; their trainers read whole arrays (NumPy ``.npy`` for
NBVNet, MA-SCVP and SC-Net, torch tensors for PC-NBV) whose conversion is not in their repository.
Each array is memory-mapped in the staging folder and filled in place, so an export of any size holds
about one sample in memory; a torch file is filled the same way and saved by torch at the end.
``array_rows.csv`` says which sample each row of each split holds.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from storage.export.base import Place, Run
from storage.export.options import SPLITS
from storage.export.publish import make_folder, write_text
from storage.store.location import StorageError

ARRAY_ROWS = "array_rows.csv"
PENDING = ".pending"
"""Staging subfolder of the arrays that become torch files at the end."""


@dataclass(frozen=True)
class ArrayFile:
    """One kind of array: its path below OUT (``{split}`` is replaced by the split's name), its dtype
    and one sample's shape."""

    key: str
    path: str
    dtype: type[np.generic]
    shape: tuple[int, ...]

    def relative(self, split: str) -> str:
        return self.path.format(split=split)

    @property
    def torch(self) -> bool:
        return self.path.endswith(".pt")


class SplitArrays:
    """Every `ArrayFile` of every split, filled by `put` and finished by `close`."""

    def __init__(self, run: Run, files: tuple[ArrayFile, ...]) -> None:
        self.run = run
        self.files = files
        self._arrays: dict[tuple[str, str], npt.NDArray[Any]] = {}
        self._rows: list[tuple[int, int, str]] = []
        for split in SPLITS:
            count = run.split_sizes[split]
            for spec in files:
                path = self._fill_path(spec, split)
                make_folder(path.parent, run.target)
                make_folder((run.staging / spec.relative(split)).parent, run.target)
                shape = (count, *spec.shape)
                try:
                    self._arrays[split, spec.key] = (
                        np.lib.format.open_memmap(path, mode="w+", dtype=spec.dtype, shape=shape)
                        if count
                        else np.zeros(shape, dtype=spec.dtype)
                    )
                except OSError as exc:
                    raise StorageError(
                        f"{run.target}: cannot write the export ({exc.strerror or exc}); check free space"
                    ) from None

    def _fill_path(self, spec: ArrayFile, split: str) -> Path:
        relative = spec.relative(split)
        if spec.torch:
            return self.run.staging / PENDING / (relative.replace("/", "__") + ".npy")
        return self.run.staging / relative

    def put(self, place: Place, values: dict[str, npt.ArrayLike]) -> None:
        """The sample's row of each kind of array (every key of ``files``)."""
        for spec in self.files:
            self._arrays[place.split, spec.key][place.position] = values[spec.key]
        folder = place.folder.relative_to(self.run.staging).as_posix()
        line = f"{place.split},{place.position},{place.sample_id},{folder},{place.case}\n"
        self._rows.append((SPLITS.index(place.split), place.position, line))

    def close(self) -> None:
        """Flush every array, save the torch files, and write ``array_rows.csv``."""
        for (split, key), array in self._arrays.items():
            spec = next(s for s in self.files if s.key == key)
            if isinstance(array, np.memmap):
                array.flush()
            if spec.torch:
                _save_torch(array, self.run.staging / spec.relative(split), self.run.target)
            elif not isinstance(array, np.memmap):
                np.save(self.run.staging / spec.relative(split), array)
        self._arrays.clear()
        shutil.rmtree(self.run.staging / PENDING, ignore_errors=True)
        rows = "".join(line for _, _, line in sorted(self._rows))
        write_text(self.run.staging / ARRAY_ROWS, "split,row,sample_id,folder,case\n" + rows, self.run.target)

    def facts(self) -> dict[str, Any]:
        """Per file: shape and dtype (what the provenance records)."""
        return {
            spec.relative(split): {
                "shape": [self.run.split_sizes[split], *spec.shape],
                "dtype": np.dtype(spec.dtype).name,
                "format": "torch.save of one tensor" if spec.torch else "numpy .npy",
            }
            for split in SPLITS
            for spec in self.files
        }


def _save_torch(array: npt.NDArray[Any], path: Path, target: Path) -> None:
    try:
        import torch
    except ImportError:
        raise StorageError(
            f"{target}: this layout writes torch tensors; install torch (pip install torch) and export again"
        ) from None
    tensor = torch.from_numpy(np.ascontiguousarray(array))
    try:
        torch.save(tensor, path)
    except OSError as exc:
        raise StorageError(f"{target}: cannot write the export ({exc.strerror or exc}); check free space") from None
