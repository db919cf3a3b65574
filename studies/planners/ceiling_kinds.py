"""Benchmark: which kinds of object leave a planner the most to learn (issue 43, item 3).

    python -m studies.planners.ceiling_kinds --train DATASET --config CONFIG --work NEW_DIR
        [--synthetic 60] [--seed 99] [--rotations 0,4] [--initial-views 0,8,16,24] [--workers 2]
        [--out studies/planners/results/ceiling-kinds.md --replace]

Every shared mesh (``../shared/meshes``, loaded as they are) and ``--synthetic`` fresh synthetic
shapes (``datagen objects synth --seed``, every family) are played by `datagen evaluate` with the
ceiling (``gain``: the true gains played step by step) and the floor's two plans (``fixed``, chosen
on ``--train`` by ``--fixed-from``, and ``spread``), ``--margins 2,3,4,6``. A kind is a synthetic
family or a shared mesh. Reported per kind: the ceiling's margin over the floor (coverage points
at equal views: what a perfect planner could add to a plan that needs no data), mean and largest
over its objects; then the shared meshes ordered by it. The shared meshes with the largest margin
at 4 views are written as an objects file (``--high-out``, the committed
``examples/high-ceiling-meshes.txt``): an evaluation set where planners have the most to learn, beside
the six watertight meshes of ``examples/watertight-meshes.txt``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from statistics import mean

from benchmarks.common import SHARED_MESHES, add_report_options, check_new_folder, check_report

BUDGETS = (2, 3, 4, 6)
MESH_SUFFIXES = {".obj", ".ply", ".stl", ".off", ".glb"}
HIGH_CEILING = 8
"""Shared meshes kept in the high-ceiling evaluation set."""


def objects_file(work: Path, synthetic: int, seed: int) -> tuple[Path, dict[str, str]]:
    """The objects file of every shared mesh and the synthetic shapes, and each object's kind."""
    kinds: dict[str, str] = {}
    lines = []
    for path in sorted(SHARED_MESHES.iterdir()):
        if path.suffix.lower() in MESH_SUFFIXES:
            name = f"shared-{path.stem}"
            lines.append(f"{path.resolve()} name={name}")
            kinds[name] = f"shared: {path.stem}"
    if synthetic:
        folder = work / "synthetic"
        datagen("objects", "synth", "--count", str(synthetic), "--seed", str(seed), "--out", str(folder))
        for line in (folder / "objects.txt").read_text().splitlines():
            if line.startswith("#") or not line.strip():
                continue
            path, name = line.split()[0], line.split("name=")[1].split()[0]
            lines.append(f"{(folder / path).resolve()} name={name}")
            kinds[name] = f"synthetic: {name.split('_', 2)[-1]}"
    listing = work / "objects.txt"
    listing.write_text("\n".join(lines) + "\n")
    return listing, kinds


def datagen(*args: str, capture: bool = False) -> str:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "datagen.cli.main", *args]
    done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
    if done.returncode not in (0, 1):  # 1: some objects failed, the rest were evaluated (their lines are kept)
        raise SystemExit(f"datagen {args[0]} failed ({done.returncode}): {done.stderr[-2000:]}")
    return done.stdout


def report(margins: list[dict[str, object]], kinds: dict[str, str], command: str, failures: list[str]) -> list[str]:
    """The per-kind and per-mesh tables of the ceiling's margins."""
    ceiling = {
        (str(r["object"]), int(r["views"])): r for r in margins if r["planner"] == "gain" and r["object"] != "all"
    }
    by_kind: dict[str, dict[int, list[float]]] = defaultdict(lambda: defaultdict(list))
    for (name, views), row in ceiling.items():
        if row["ceiling_margin"] is not None:
            by_kind[kinds.get(name, name)][views].append(float(row["ceiling_margin"]))  # type: ignore[arg-type]
    heads = " | ".join(f"{v} views mean / max" for v in BUDGETS)
    lines = [
        "# Where the ceiling is large: the true gains' margin over the floor, by kind of object",
        "",
        f"Command: `{command}`",
        "",
        "The floor at V views is the better of the best fixed view set (chosen on the training set) and",
        "views spread from the initial one; the ceiling is the true gains played step by step (`gain`).",
        "Margins in coverage points (percent of what all views see), per object averaged over its runs.",
        "",
        f"| kind | objects | {heads} |",
        "|---|---:|" + "---:|" * len(BUDGETS),
    ]
    order = sorted(by_kind, key=lambda kind: -mean(by_kind[kind].get(4, [0.0]) or [0.0]))
    for kind in order:
        cells = [
            f"{mean(values):.2f} / {max(values):.2f}" if (values := by_kind[kind].get(v)) else "-" for v in BUDGETS
        ]
        count = max(len(values) for values in by_kind[kind].values())
        lines.append(f"| {kind} | {count} | " + " | ".join(cells) + " |")
    if failures:
        lines += ["", "Objects that could not be evaluated (left out):", "", *(f"- {line}" for line in failures)]
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--train", required=True, help="the training dataset the fixed plans are chosen on")
    parser.add_argument("--config", type=Path, required=True, help="the generation config (the training set's)")
    parser.add_argument("--work", type=Path, required=True, help="a new or empty folder")
    parser.add_argument("--synthetic", type=int, default=60, help="fresh synthetic shapes (0: the shared meshes only)")
    parser.add_argument("--seed", type=int, default=99, help="their seed (not the training set's)")
    parser.add_argument("--rotations", default="0,4")
    parser.add_argument("--initial-views", default="0,8,16,24")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument(
        "--high-out",
        type=Path,
        default=Path(__file__).resolve().parents[2] / "examples" / "high-ceiling-meshes.txt",
        help="where the high-ceiling evaluation set is written with --out",
    )
    add_report_options(parser)
    args = parser.parse_args(argv)
    check_new_folder(parser, args.work)
    check_report(parser, args.out, args.replace)
    args.work.mkdir(parents=True, exist_ok=True)
    listing, kinds = objects_file(args.work, args.synthetic, args.seed)
    evaluate = ["evaluate", "--objects", str(listing), "--config", str(args.config), "-p", "gain", "-p", "spread"]
    evaluate += ["-p", "fixed", "--fixed-from", args.train, "--rotations", args.rotations]
    evaluate += ["--initial-views", args.initial_views, "--margins", ",".join(map(str, BUDGETS))]
    evaluate += ["--workers", str(args.workers), "--json"]
    found = json.loads(datagen(*evaluate))
    (args.work / "evaluate.json").write_text(json.dumps(found) + "\n")
    command = "python -m studies.planners.ceiling_kinds " + " ".join(sys.argv[1:] if argv is None else argv)
    lines = report(found["margins"], kinds, command, found.get("failures", []))
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None:
        args.out.write_text(text)
        high = sorted(
            (r for r in found["margins"] if r["planner"] == "gain" and r["views"] == 4 and r["object"] != "all"),
            key=lambda r: -(r["ceiling_margin"] or 0.0),
        )
        chosen = [str(r["object"]).removeprefix("shared-") for r in high if str(r["object"]).startswith("shared-")]
        paths = {p.stem: p for p in SHARED_MESHES.iterdir()}
        picked = [paths[name] for name in chosen[:HIGH_CEILING] if name in paths]
        relative = [os.path.relpath(p, args.high_out.parent.resolve()) for p in picked]
        header = "# The shared meshes with the largest margin of the true gains over the floor at 4 views\n"
        header += f"# ({args.out}, written by studies/planners/ceiling_kinds.py): where a planner has the most\n"
        header += "# to learn. Paths resolve against this file's folder.\n"
        args.high_out.write_text(header + "\n".join(relative) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
