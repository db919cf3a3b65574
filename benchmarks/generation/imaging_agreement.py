"""Measured agreement of our imaging with Open3D on the real meshes (the numbers behind the imaging tests).

    python -m benchmarks.generation.imaging_agreement [--meshes DIR]

For every mesh of DIR (default ../shared/meshes), prepared at size 0.15 m, rotation 0, it prints: faces,
|P_gt| as sampled, the union of the 32 views' visible keys in both imaging modes, the share of the
pixels-mode union that the sampled P_gt holds, the per-view Jaccard index against Open3D (min/mean per
mode), the median number of keys only one view sees, and the largest distance of a P_gt key centre to
the surface in voxels (its bound is half a voxel diagonal, 0.866). The tests in
``tests/pipeline/test_imaging_shared.py`` assert bounds on the same numbers.
"""

from __future__ import annotations

from benchmarks.common import SHARED_MESHES, limit_threads, use_test_support

limit_threads()
use_test_support()

import argparse  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from support.imaging_agreement import TARGETS, mesh_result  # noqa: E402

MESH_SUFFIXES = {".obj", ".ply", ".stl", ".off", ".glb"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--meshes", type=Path, default=SHARED_MESHES)
    args = parser.parse_args()
    meshes = sorted(p for p in args.meshes.glob("*") if p.suffix.lower() in MESH_SUFFIXES)
    if not meshes:
        raise SystemExit(f"no meshes in {args.meshes}: pass --meshes DIR")
    print(
        f"{'mesh':20} {'faces':>7} {'P_gt':>6} {'U tgt':>6} {'U pix':>6} {'pix smp%':>8} "
        f"{'J tgt min/mean':>16} {'J pix min/mean':>16} {'1-view med tgt/pix':>18} {'dmax/vox':>8}"
    )
    for path in meshes:
        r = mesh_result(path)
        t, p = r.modes["targets"], r.modes["pixels"]
        fraction = 100 * np.isin(p.union, r.sampled.keys).mean()
        print(
            f"{path.name:20} {r.faces:7d} {len(r.sampled):6d} {t.union.size:6d} {p.union.size:6d} {fraction:8.2f} "
            f"{t.jaccard.min():7.5f}/{t.jaccard.mean():8.6f} {p.jaccard.min():7.5f}/{p.jaccard.mean():8.6f} "
            f"{np.median(t.single_view_counts()):9.1f}/{np.median(p.single_view_counts()):8.1f} "
            f"{r.centre_distance.max() / TARGETS.voxel_size:8.4f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
