"""Benchmark: how long a listing command takes to start, against the code of a baseline commit in the same run.

    python -m benchmarks.reading.cli_startup [--baseline COMMIT] [--repeats 7] [--url DATASET]
        [--out benchmarks/reading/results/cli-startup.md --replace]

Each command runs as a fresh process, ``--repeats`` times in turns with the baseline's, and the median
wall seconds are reported with their ratio: ``datagen status`` on an empty ledger (all of it is start-up:
imports and the ledger), ``datagen --help`` and, with ``--url``, ``datagen shards ls URL`` (start-up plus
reading the index). The baseline is the given commit checked out with ``git worktree`` into a temporary
folder and imported from there (``PYTHONPATH``), with this checkout's installed dependencies.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import REPO_ROOT, add_report_options, check_report

LAUNCH = "import sys; from datagen.cli.main import app; sys.argv = ['datagen', *sys.argv[1:]]; app()"


def timed(source: Path, args: list[str]) -> float:
    """Wall seconds of one ``datagen ARGS`` run from the code at ``source``."""
    env = {**os.environ, "PYTHONPATH": str(source), "OPENBLAS_NUM_THREADS": "1"}
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", LAUNCH, *args], cwd=source, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if done.returncode not in (0, 1):
        raise SystemExit(f"datagen {' '.join(args)} from {source} failed: {done.stderr[-400:]}")
    return seconds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--baseline", default="5ede63e", help="the commit to compare with (default: before issue 52)")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--url", default=None, help="a dataset for `shards ls`")
    add_report_options(parser)
    args = parser.parse_args(argv)
    check_report(parser, args.out, args.replace)
    with tempfile.TemporaryDirectory() as folder:
        home, baseline = Path(folder) / "home", Path(folder) / "baseline"
        subprocess.run(["git", "-C", str(REPO_ROOT), "worktree", "add", "--detach", str(baseline), args.baseline],
                       check=True, capture_output=True)  # fmt: skip
        try:
            commands = {"status": ["status", "--home", str(home)], "--help": ["--help"]}
            if args.url:
                commands["shards ls"] = ["shards", "ls", args.url]
            rows = []
            for name, command in commands.items():
                times: dict[str, list[float]] = {"baseline": [], "head": []}
                for _ in range(args.repeats):  # in turns, so a busier moment weighs on both alike
                    times["baseline"].append(timed(baseline, command))
                    times["head"].append(timed(REPO_ROOT, command))
                before, after = (statistics.median(times[k]) for k in ("baseline", "head"))
                rows.append(f"| `datagen {name}` | {before:.2f} | {after:.2f} | {after / before:.2f}x |")
        finally:
            subprocess.run(["git", "-C", str(REPO_ROOT), "worktree", "remove", "--force", str(baseline)], check=False)
    lines = [
        f"Start-up of listing commands, median of {args.repeats} runs each, in turns with the code of "
        f"{args.baseline} (the baseline) in the same run.",
        "",
        f"| command | baseline s ({args.baseline}) | this checkout s | ratio |",
        "|---|---:|---:|---:|",
        *rows,
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None:
        command = "python -m benchmarks.reading.cli_startup " + " ".join(argv if argv is not None else sys.argv[1:])
        args.out.write_text(f"Made by `{command}`.\n\n{text}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
