"""Benchmark: our 32-view imaging against Open3D's raw ray casting of exactly the same rays.

    python -m benchmarks.generation.imaging [--meshes DIR] [--repeats 3] [--profile MESH]

For every mesh of DIR (default ../shared/meshes), prepared at size 0.15 m, rotation 0, and for both
imaging modes, it prints:

- rays: rays cast over the 32 views (the same for both sides);
- ours s: `datagen.pipeline.imaging.image_task` for all 32 views (ray generation + Embree cast + float64
  refinement + keying + observations), with P_gt precomputed and the Embree scene prebuilt, both
  excluded;
- our cast s: `RayCaster.first_hits` alone on the prebuilt rays (Embree cast + float64 refinement),
  to show how much of "ours" is the cast;
- o3d s: Open3D `RaycastingScene.cast_rays(..., nthreads=1)` alone on the same rays, built once as
  float32 tensors (one call per view, as ours), scene prebuilt;
- ours/o3d: the ratio (target <= 1.5).

Everything is single-threaded (OPENBLAS/OMP threads 1, Open3D nthreads=1; our caster is single
threaded by design). Times are process CPU seconds (robust to other processes sharing the cores),
the median of ``--repeats`` rounds after one warm-up round, measured in the same process, with the
three timed calls interleaved round-robin so that remaining machine noise hits all sides alike.
"""

from __future__ import annotations

from benchmarks.common import SHARED_MESHES, limit_threads, use_test_support

limit_threads()
use_test_support()

import argparse  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from support.open3d_reference import Intrinsics, Open3DCaster, pixel_rays, target_rays  # noqa: E402

from datagen.pipeline.ground_truth import GroundTruth, sample_ground_truth  # noqa: E402
from datagen.pipeline.imaging import SPHERE_MARGIN, image_task  # noqa: E402
from datagen.pipeline.objects.prepare import prepare_object  # noqa: E402
from datagen.pipeline.objects.spec import ObjectOptions, mesh_file_spec  # noqa: E402
from datagen.pipeline.random_streams import Purpose, stream  # noqa: E402
from datagen.pipeline.raycast import RayCaster  # noqa: E402
from datagen.pipeline.viewspace import build_view_space  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402

MESH_SUFFIXES = {".obj", ".ply", ".stl", ".off", ".glb"}
SIZE_M = 0.15
MODES = ("targets", "pixels")


def median_seconds(functions: list[Callable[[], object]], repeats: int) -> list[float]:
    """Median CPU seconds of each function over ``repeats`` rounds after a warm-up round.

    The functions run round-robin (a, b, c, a, b, c, ...) so that a slow phase of the machine hits
    all of them. CPU time of the process (all its threads), not wall time: on a shared 2-core
    machine other processes preempt this one and inflate wall time at random, and everything timed
    here is single-threaded, so CPU time is the work done.
    """
    for function in functions:
        function()  # warm-up
    times: list[list[float]] = [[] for _ in functions]
    for _ in range(repeats):
        for index, function in enumerate(functions):
            started = time.process_time()
            function()
            times[index].append(time.process_time() - started)
    return [statistics.median(t) for t in times]


def timing_row(name: str, mode: str, faces: str, rays: float, ours_s: float, cast_s: float, o3d_s: float) -> list[str]:
    """One row of the table: the three timings, their ratios to Open3D's and our rays per second."""
    return [
        name,
        mode,
        faces,
        f"{int(rays):,}",
        f"{ours_s:.3f}",
        f"{cast_s:.3f}",
        f"{o3d_s:.3f}",
        f"{ours_s / o3d_s:.2f}",
        f"{cast_s / o3d_s:.2f}",
        f"{rays / ours_s / 1e6:.1f}",
    ]


def prepare(path: Path, config: GenerationConfig):
    spec = mesh_file_spec(path, ObjectOptions(size=SIZE_M))
    prepared = prepare_object(spec, config)
    vertices = prepared.task_vertices(0, config.rotations)
    ground_truth = sample_ground_truth(
        vertices,
        prepared.faces,
        config.voxel_size,
        config.grid_offset,
        config.gt_density,
        stream(config.seed, spec.object_id, 0, Purpose.GROUND_TRUTH),
    )
    return vertices, prepared.faces, ground_truth


def reference_views(mode: str, vertices: np.ndarray, ground_truth: GroundTruth, config: GenerationConfig, positions):
    camera = Intrinsics.of(config.camera)
    if mode == "targets":
        return target_rays(camera, positions, ground_truth.points)
    radius = float(np.sqrt((vertices**2).sum(axis=1).max())) * (1.0 + SPHERE_MARGIN)
    return pixel_rays(camera, positions, radius)


def format_table(rows: list[list[str]], header: list[str]) -> str:
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    lines = []
    for index, row in enumerate([header, *rows]):
        cells = [cell.ljust(widths[i]) if i < 2 else cell.rjust(widths[i]) for i, cell in enumerate(row)]
        lines.append("  ".join(cells))
        if index == 0 or (index == len(rows) and rows and rows[-1][0] == "TOTAL"):
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", type=Path, default=SHARED_MESHES)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--profile", metavar="MESH", help="also cProfile one image_task per mode on this mesh")
    args = parser.parse_args()

    paths = (
        sorted(p for p in args.meshes.iterdir() if p.suffix.lower() in MESH_SUFFIXES) if args.meshes.is_dir() else []
    )
    if not paths:
        print(f"no meshes found in {args.meshes}", file=sys.stderr)
        return 1
    view_space = build_view_space(GenerationConfig().view_space)
    configs = {mode: GenerationConfig(imaging=mode) for mode in MODES}
    header = [
        "mesh",
        "mode",
        "faces",
        "rays",
        "ours s",
        "our cast s",
        "o3d s",
        "ours/o3d",
        "cast/o3d",
        "Mrays/s ours",
    ]
    rows: list[list[str]] = []
    totals = {mode: [0, 0.0, 0.0, 0.0] for mode in MODES}
    started = time.perf_counter()
    for path in paths:
        vertices, faces, ground_truth = prepare(path, configs["targets"])
        caster = RayCaster(vertices, faces)
        reference = Open3DCaster(vertices, faces)
        for mode in MODES:
            config = configs[mode]
            views = reference_views(mode, vertices, ground_truth, config, view_space.positions)
            tensors = [view.as_open3d() for view in views]
            rays = sum(view.directions.shape[0] for view in views)

            def ours(config=config, caster=caster, vertices=vertices, faces=faces, ground_truth=ground_truth):
                return image_task(vertices, faces, ground_truth, view_space, config, caster)

            def our_cast(views=views, caster=caster, config=config):
                for view in views:
                    caster.first_hits(view.origin, view.directions, config.camera.max_range)

            def theirs(tensors=tensors, reference=reference):
                for tensor in tensors:
                    reference.cast_raw(tensor, nthreads=1)

            imaging = ours()
            if imaging.rays_cast != rays:
                raise SystemExit(f"{path.name} {mode}: ours cast {imaging.rays_cast} rays, the reference {rays}")
            ours_s, cast_s, o3d_s = median_seconds([ours, our_cast, theirs], args.repeats)
            rows.append(timing_row(path.name, mode, str(len(faces)), rays, ours_s, cast_s, o3d_s))
            total = totals[mode]
            total[0] += rays
            total[1] += ours_s
            total[2] += cast_s
            total[3] += o3d_s
        print(f"  {path.name}: done ({time.perf_counter() - started:.0f} s)", file=sys.stderr, flush=True)
    grand = [sum(t[i] for t in totals.values()) for i in range(4)]
    for label, (rays, ours_s, cast_s, o3d_s) in [
        *((f"TOTAL {m}", totals[m]) for m in MODES),
        ("TOTAL", grand),
    ]:
        name, mode = [*label.split(), ""][:2] if label != "TOTAL" else ("TOTAL", "both")
        rows.append(timing_row(name, mode, "", rays, ours_s, cast_s, o3d_s))
    print()
    print(
        "32-view imaging, single-threaded, CPU seconds, median of "
        f"{args.repeats} after a warm-up; sizes {SIZE_M} m, rotation 0 (target: ours/o3d <= 1.5)"
    )
    print(format_table(rows, header))
    print(f"\nwall time {time.perf_counter() - started:.0f} s")

    if args.profile:
        path = next((p for p in paths if p.name == args.profile or p.stem == args.profile), None)
        if path is None:
            print(f"--profile: no mesh named {args.profile}", file=sys.stderr)
            return 1
        vertices, faces, ground_truth = prepare(path, configs["targets"])
        caster = RayCaster(vertices, faces)
        for mode in MODES:
            profiler = cProfile.Profile()
            profiler.enable()
            image_task(vertices, faces, ground_truth, view_space, configs[mode], caster)
            profiler.disable()
            print(f"\ncProfile of image_task, {path.name}, {mode}:")
            pstats.Stats(profiler).sort_stats("tottime").print_stats(14)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
