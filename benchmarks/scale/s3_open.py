"""Opening a large dataset from a real S3 server (SeaweedFS on loopback, the compose cluster's store):
seconds and requests against the task count.

    python -m benchmarks.scale.s3_open --data after=/work/runs/scale/tasks-1000 [--data ...] \\
        [--with-shards 10000] [--work /tmp/datagen-scale-s3] --out benchmarks/scale/results/s3-open.md

Each ``--data LABEL=PATH`` (a local dataset made by `benchmarks.scale.datasets`, by the tree named
``LABEL``: ``after`` is this checkout, any other label's tree comes first on ``PYTHONPATH`` as
``--source LABEL=TREE`` says) is uploaded to SeaweedFS (32 uploads side by side), then
`storage.open_dataset` runs in a fresh process of that tree (`benchmarks/scale/probe.py`), which
counts every request s3fs sends, and so do ``shards ls`` and ``shards stats`` (run in the probe's
process); datasets of at most ``--with-shards`` tasks are uploaded whole and one sample is read too,
larger ones without their shard files (what opening, ``ls`` and ``stats`` read: ``dataset.json``, the
records and the index), which a 100,000-task upload would spend most of its time on.
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from benchmarks.common import add_report_options, check_report, use_test_support
from benchmarks.scale.measure import Measurement, machine_line, run_measured
from benchmarks.scale.objects import source_env

PROBE = Path(__file__).with_name("probe.py")
UPLOADS = 32


def upload(server: object, root: Path, prefix: str, shards: bool) -> int:
    """Every file of the dataset at ``root`` (without ``shards/`` unless ``shards``) under ``prefix``."""
    client = server.client()  # type: ignore[attr-defined]
    files = [
        path
        for path in sorted(root.rglob("*"))
        if path.is_file() and (shards or path.relative_to(root).parts[0] != "shards")
    ]

    def put(path: Path) -> None:
        client.upload_file(str(path), "datasets", f"{prefix}/{path.relative_to(root).as_posix()}")

    with ThreadPoolExecutor(max_workers=UPLOADS) as pool:
        list(pool.map(put, files))
    return len(files)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", action="append", required=True, help="LABEL=PATH")
    parser.add_argument("--source", action="append", default=[], help="LABEL=TREE (default: after=.)")
    parser.add_argument("--with-shards", type=int, default=10_000)
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "datagen-scale-s3")
    add_report_options(parser)
    args = parser.parse_args()
    check_report(parser, args.out, args.replace)
    trees = {"after": Path(".").resolve(), **{k: Path(v).resolve() for k, v in (s.split("=", 1) for s in args.source)}}
    use_test_support()
    from support.s3_servers import seaweedfs_server

    args.work.mkdir(parents=True, exist_ok=True)
    rows = []
    with seaweedfs_server(args.work / "seaweedfs") as server:
        for item in args.data:
            label, path = item.split("=", 1)
            root = Path(path)
            tasks = len(os.listdir(root / "commits"))
            whole = tasks <= args.with_shards
            prefix = f"{label}-{root.name}"
            files = upload(server, root, prefix, whole)
            env = {**source_env(trees[label], os.environ), **server.env()}
            url = f"s3://datasets/{prefix}"
            for operation in ("open", "sample", "ls", "stats") if whole else ("open", "ls", "stats"):
                report = args.work / "report.json"
                found = run_measured(
                    [sys.executable, str(PROBE), operation, url, str(report)],
                    cwd=trees[label],
                    env=env,
                    stdout=args.work / f"{prefix}-{operation}.log",
                    report=report,
                )
                rows.append((label, tasks, files, operation, found))
                print(f"{label} {tasks} {operation}: {found}", file=sys.stderr, flush=True)
    text = report_text(rows)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


def report_text(rows: list[tuple[str, int, int, str, Measurement]]) -> str:
    lines = [
        "# Scale: opening a dataset on S3 (SeaweedFS on loopback)",
        "",
        f"Made by `python -m benchmarks.scale.s3_open` on {datetime.date.today().isoformat()}: {machine_line()}.",
        "Seconds: the operation's own (imports apart); requests: every call s3fs sent. Files: what was",
        "uploaded (a dataset larger than `--with-shards` tasks without its shard files: opening reads none).",
        "",
        "| tree | tasks | files uploaded | operation | seconds | requests | peak MB |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, tasks, files, operation, found in rows:
        seconds = found.extra.get("seconds", found.wall)
        requests = found.extra.get("requests", "")
        failed = "" if found.rc == 0 else f" (rc {found.rc})"
        cells = [label, f"{tasks:,}", f"{files:,}", f"{operation}{failed}", f"{seconds:.2f}", str(requests)]
        lines.append("| " + " | ".join([*cells, f"{found.peak_mb:.0f}"]) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
