"""``datagen shards ls | show | stats``: what a dataset holds, read from its URL alone.

Thin wrappers over `datagen.inspection`; tables are laid out for an 80-column terminal (short
headers, long values folded onto more lines rather than cut). matplotlib is imported only for --png.
Plain functions; `datagen.cli.shards` registers them.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich import box
from rich.table import Table

from datagen.cli.common import Cell, UrlArgument, dataset_options, plural, print_rows, print_table, say, user_errors
from datagen.errors import OutputError

if TYPE_CHECKING:  # the dataset's reader and inspection tools load when a command runs, not at every start
    from datagen.inspection.listing import SampleDetails, TaskRow
    from datagen.inspection.stats import DatasetStats

PngOption = Annotated[Path | None, typer.Option("--png", metavar="FILE", help="Also draw it to this PNG file.")]


def format_bytes(count: int) -> str:
    """Bytes in binary units with three significant digits (``812 B``, ``10.6 KiB``, ``1.25 MiB``)."""
    value = float(count)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if value < 1024 or unit == "TiB":
            return f"{count} B" if unit == "B" else f"{value:.3g} {unit}"
        value /= 1024
    raise AssertionError("unreachable")


def format_seconds(seconds: float | None) -> str:
    """Three significant digits in s, ms or µs."""
    if seconds is None:
        return "-"
    if seconds >= 1:
        return f"{seconds:.3g} s"
    return f"{seconds * 1e3:.3g} ms" if seconds >= 1e-3 else f"{seconds * 1e6:.3g} µs"


def format_views(views: Sequence[int]) -> str:
    return " ".join(str(v) for v in views) if views else "none"


def view_strip(details: SampleDetails) -> str:
    """One character per view, in bit order: I input, L label, B both, a view of another minimum cover
    (version 2), . other."""
    from storage.samples import mask_bits

    support = mask_bits(details.ambiguity.support if details.ambiguity else 0, details.num_views).tolist()
    marks = []
    for view in range(details.num_views):
        chosen = (view in details.input_views, view in details.label_views)
        other = "a" if support[view] else "."
        marks.append({(True, False): "I", (False, True): "L", (True, True): "B"}.get(chosen, other))
    return "".join(marks)


def ambiguity_rows(details: SampleDetails) -> list[tuple[str, str]]:
    """``shards show`` lines on the label's minimum covers (none for a version-1 dataset)."""
    import numpy as np

    from storage.samples import mask_bits

    found = details.ambiguity
    if found is None:
        return [("minimum covers", "not recorded (schema 1; `datagen shards relabel` adds them)")]
    count = f"{found.count}" if found.exact else f"at least {found.count}"
    marginals = found.marginals(details.num_views)
    shares = "  ".join(f"{v}:{marginals[v]:.2f}" for v in range(details.num_views) if marginals[v] > 0)
    support_views = np.flatnonzero(mask_bits(found.support, details.num_views)).tolist()
    listed = "" if found.exact else f" (marginals over the {len(found.covers)} listed)"
    return [
        ("minimum covers", f"{count}; the label is one of them"),
        ("support", f"{format_views(support_views)}  (views of any minimum cover)"),
        ("marginals", (shares or "none") + listed),
    ]


def next_view_rows(details: SampleDetails) -> list[tuple[str, str]]:
    """The next-view labels (version 3): the best view and the largest gains of both kinds."""
    found = details.next_view
    if found is None:
        return []
    if found.best_view < 0:
        best = "none (the case has every view)"
    else:
        gain = int(found.view_gains[found.best_view])
        share = gain / found.visible_size if found.visible_size else 0.0
        unique = "unique" if found.best_view_ties == 1 else f"{found.best_view_ties} views tie"
        best = f"view {found.best_view}: +{gain} keys, {share:.1%} of what any view sees ({unique})"
    return [
        ("best next view", best),
        ("view gains", _top_gains(found.view_gains, found.visible_size, "of V")),
        ("coverage gains", _top_gains(found.coverage_gains, found.full_size, "of P_full")),
    ]


def _top_gains(gains: Any, total: int, of: str, shown: int = 5) -> str:
    """The ``shown`` largest gains as ``view:share``, largest first, lowest view among equals."""
    order = sorted(range(len(gains)), key=lambda v: (-int(gains[v]), v))[:shown]
    text = "  ".join(f"{v}:{int(gains[v]) / total:.1%}" if total else f"{v}:0" for v in order)
    return f"{text}  (largest {shown}, share {of})"


def _table(*headers: str, title: str | None = None) -> Table:
    table = Table(title=title, box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True, title_justify="left")
    for header in headers:
        numeric = header in {"rot", "samples", "points", "size", "cases", "empty", "p0", "p5", "p50", "p95", "p100"}
        whole = numeric or header == "task"  # a task id reads (and is copied) best on one line
        table.add_column(header, justify="right" if numeric else "left", overflow="fold", no_wrap=whole)
    return table


def write_png(path: Path, image: bytes, quiet: bool = False) -> None:
    """Write a picture; ``quiet`` keeps stdout for JSON alone."""
    try:
        path.write_bytes(image)
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}; give a writable --png path") from None
    if not quiet:
        say(f"wrote {path}")


# -- ls -------------------------------------------------------------------------------------------


TASK_COLUMNS = ["task", "object", "rot", "samples", "points", "size", "state"]


def task_cells(row: TaskRow) -> list[Cell]:
    """One task's row of ``shards ls``."""
    from datagen.inspection.listing import FAILED

    stored = row.state != FAILED
    return [
        row.task_id,
        row.object_name or "-",
        "-" if row.rotation is None else str(row.rotation),
        str(row.samples) if stored else "-",
        str(row.points) if stored else "-",
        format_bytes(row.bytes_on_disk) if stored else "-",
        row.state,
    ]


def ls(
    url: UrlArgument,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object (every task, then the totals).")] = False,
) -> None:
    """One row per task: object, rotation, samples, points in its refined clouds, bytes on disk, and
    whether it committed; each failed task's message follows the table."""
    from datagen.inspection.listing import FAILED, list_tasks
    from storage import open_dataset

    with user_errors(url):
        rows = list_tasks(open_dataset(url, dataset_options(url)))
    if as_json:
        _print_tasks_json(rows)
        return
    print_rows(TASK_COLUMNS, (task_cells(row) for row in rows), whole=["task"])  # tab-separated off a terminal
    failed = [row for row in rows if row.state == FAILED]
    committed = len(rows) - len(failed)
    total = sum(row.bytes_on_disk for row in rows)
    say(f"{committed} committed ({sum(r.samples for r in rows)} samples, {format_bytes(total)}), {len(failed)} failed")
    for row in failed:
        origin = f" ({row.origin})" if row.origin else ""
        say(f"failed {row.task_id}{origin}: {row.message}")


def _print_tasks_json(rows: list[TaskRow]) -> None:
    """`ls --json`: ``{"tasks": [...], "committed", "failed", "samples", "bytes"}``, a task a line."""
    from datagen.inspection.listing import FAILED

    out = sys.stdout
    out.write('{"tasks": [')
    for number, row in enumerate(rows):
        out.write(("," if number else "") + "\n" + json.dumps(dataclasses.asdict(row)))
    failed = sum(row.state == FAILED for row in rows)
    totals = {
        "committed": len(rows) - failed,
        "failed": failed,
        "samples": sum(row.samples for row in rows),
        "bytes": sum(row.bytes_on_disk for row in rows),
    }
    out.write("\n], " + json.dumps(totals)[1:] + "\n")
    out.flush()


# -- show -----------------------------------------------------------------------------------------


def sample_table(details: SampleDetails) -> Table:
    meta: dict[str, Any] = details.metadata
    table = Table(box=None, show_header=False, pad_edge=False)
    table.add_column("field", style="bold", no_wrap=True)
    table.add_column("value", overflow="fold")
    rows = [
        ("sample", f"{meta['sample_id']} (row {details.row})"),
        ("object", f"{meta['object_name']} (id {meta['object_id'][:16]}), rotation {meta['rotation']}"),
        ("shard", f"{meta['shard']} row {meta['row']}"),
        ("input views", f"{format_views(details.input_views)}  ({plural(len(details.input_views), 'view')})"),
        ("label views", f"{format_views(details.label_views)}  ({plural(len(details.label_views), 'view')})"),
        ("views", f"{view_strip(details)}  (I input, L label, a another minimum cover)"),
        *ambiguity_rows(details),
        *next_view_rows(details),
        ("points", f"{details.points} refined P(O_S), {details.observed} observed keys(O_S)"),
        ("sets", f"|P_full| {meta['full_size']}, |U| {meta['universe_size']}"),
        ("solver", f"{meta['solver_status']}, proof {meta['solver_proof']}, objective {meta['solver_objective']}"),
        ("solver time", format_seconds(meta["solver_seconds"])),
        ("cover rows", f"{meta['rows_before']} -> {meta['rows_after']} after merging and dominance"),
        ("refiner", f"{meta['refiner']} (weights {meta['weights_id'] or '-'}, {meta['device']}), seed {meta['seed']}"),
        ("config", f"{meta['config_hash'][:16]}, schema {meta['schema_version']}"),
    ]
    for field, value in rows:
        table.add_row(field, value)
    return table


def show(
    url: UrlArgument,
    sample: Annotated[str, typer.Argument(metavar="SAMPLE", help="An index row number or a sample id.")],
    png: PngOption = None,
) -> None:
    """One sample: its metadata, input and label views, point counts and solver record; --png draws
    its clouds and views."""
    from datagen.inspection.listing import describe_sample, find_sample
    from storage import open_dataset

    with user_errors(url):
        dataset = open_dataset(url, dataset_options(url))
        details = describe_sample(dataset, find_sample(dataset, sample))
        print_table(sample_table(details))
        if png is not None:
            from datagen.inspection.plots import draw_sample

            row = details.row
            image = draw_sample(
                dataset.centres(dataset.keys(row, "points")),
                dataset.centres(dataset.keys(row, "observed")),
                dataset.info.view_positions,
                details.input_views,
                details.label_views,
                title=f"{details.metadata['sample_id']} ({details.metadata['object_name']})",
            )
            write_png(png, image)


# -- stats ----------------------------------------------------------------------------------------


def _histogram_text(histogram: dict[int, int]) -> str:
    return "  ".join(f"{size}:{count}" for size, count in histogram.items())


def print_stats(stats: DatasetStats) -> None:
    from datagen.pipeline.step_timing import step_lines

    say(
        f"{stats.samples} samples in {stats.committed_tasks} committed tasks, {len(stats.failed)} failed; "
        f"{stats.empty_labels} empty labels"
    )
    say(f"labels: {stats.objective}")
    rotations: dict[str, dict[int, int]] = {}
    for counted in stats.samples_per_task:  # one pass: an object's rotations looked up, not searched for
        rotations.setdefault(counted.object_name, {})[counted.rotation] = counted.samples
    say("samples per object")
    print_rows(
        ["object", "samples", "per rotation (rotation:samples)"],
        (
            [name, str(count), _histogram_text(rotations.get(name, {}))]
            for name, count in stats.samples_per_object.items()
        ),
    )

    per_case = _table("|S|", "cases", "empty", "label sizes (|L|:cases)", title="cases per case size")
    for case_size, count in stats.cases_per_case_size.items():
        labels = stats.label_sizes.get(case_size, {})
        per_case.add_row(str(case_size), str(count), str(labels.get(0, 0)), _histogram_text(labels))
    print_table(per_case)

    spread = _table("per sample", "p0", "p5", "p50", "p95", "p100", title="percentiles")
    spread.add_row("points", *("-" if v is None else f"{v:.0f}" for v in stats.points_percentiles.values()))
    spread.add_row("solver time", *(format_seconds(v) for v in stats.solver_seconds_percentiles.values()))
    print_table(spread)
    say("proofs: " + (", ".join(f"{kind} {count}" for kind, count in stats.solver_proofs.items()) or "none"))
    print_ambiguity(stats)
    print_next_view(stats)
    for line in step_lines(stats.step_seconds):
        say(line)

    if stats.failed:
        failed = _table("task", "object", "message", title="failed tasks")
        for task in stats.failed:
            failed.add_row(task.task_id, task.object_name or "-", task.message)
        print_table(failed)


def print_ambiguity(stats: DatasetStats) -> None:
    """How many minimum covers (another objective: ties) the (non-empty) labels were chosen from."""
    from schemas.objectives import objective_named

    found = stats.ambiguity
    if found is None:
        say("minimum covers: not recorded (schema 1; `datagen shards relabel URL --out URL2` adds them)")
        return
    many, unique = objective_named(stats.objective).ties_words
    table = _table("|S|", unique, f"median {many}", title="label ambiguity (non-empty labels)")
    for name, share in found.unique.items():
        table.add_row(name, f"{share:.1%}", f"{found.median_covers[name]:.0f}")
    print_table(table)
    spread = _table("per label", "p0", "p5", "p50", "p95", "p100")
    spread.add_row(many, *("-" if v is None else f"{v:.0f}" for v in found.count_percentiles.values()))
    spread.add_row(
        "support views", *("-" if v is None else f"{v:.0f}" for v in found.support_size_percentiles.values())
    )
    print_table(spread)
    if found.capped:
        say(f"{found.capped} labels have more {many} than the cap: their counts are lower bounds")


def print_next_view(stats: DatasetStats) -> None:
    """How often the best next view is unique, and how much it adds (version 3)."""
    found = stats.next_view
    if found is None:
        say("next-view labels: not recorded (before schema 3; `datagen shards relabel URL --out URL2` adds them)")
        return
    table = _table("|S|", "unique best view", title="best next view")
    for name, share in found.unique.items():
        table.add_row(name, f"{share:.1%}")
    print_table(table)
    spread = _table("per sample", "p0", "p5", "p50", "p95", "p100")
    spread.add_row("best gain share", *("-" if v is None else f"{v:.3f}" for v in found.best_gain_share.values()))
    print_table(spread)
    width = 1.0 / len(found.best_gain_histogram)
    bins = "  ".join(f"{i * width:.1f}:{n}" for i, n in enumerate(found.best_gain_histogram))
    for line in textwrap.wrap(f"best gain share histogram (bin start:samples): {bins}", 80):
        say(line)
    for line in textwrap.wrap("best view (view:samples): " + _histogram_text(found.best_view_counts), 80):
        say(line)
    if found.no_next_view:
        say(f"{found.no_next_view} samples have every view (no next view)")


def stats(
    url: UrlArgument,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object instead of tables.")] = False,
    png: PngOption = None,
) -> None:
    """Samples per object and rotation, cases and label sizes per case size, empty labels, points and
    solver time percentiles, time per task step, failed tasks; --json for machines, --png for the
    histograms."""
    from datagen.inspection.stats import dataset_stats
    from storage import open_dataset

    with user_errors(url):
        summary = dataset_stats(open_dataset(url, dataset_options(url)))
        if as_json:
            typer.echo(json.dumps(summary.to_json(), indent=1))
        else:
            print_stats(summary)
        if png is not None:
            from datagen.inspection.plots import draw_stats

            write_png(png, draw_stats(summary), quiet=as_json)
