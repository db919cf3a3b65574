"""``datagen shards validate | digest | relabel``: is a dataset right, is it the same as another, and
the same samples for another alpha.

``validate`` joins two checkers in one pass over the shards: `storage.validate` (structure, index,
commit and failure records agreeing, every checked label covers its U; numpy only) and
`datagen.inspection.label_check` (each objective's checker: for ``cover`` minimality and the
lexicographic tie-break, with a solver) as its per-shard hook, so each shard is read once. Where
both see the same damage, the line is printed once. Warnings (harmless leftovers) follow the
problems and never fail the command. Plain functions; `datagen.cli.shards` registers them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

import typer

from datagen.cli.common import UrlArgument, dataset_options, plural, progress_bar, say, user_errors
from storage.dataset import Mend, Problem, lines

if TYPE_CHECKING:
    from datagen.inspection.label_check import LabelProblem


def digest(
    urls: Annotated[list[str], typer.Argument(help="Datasets (paths or fsspec URLs).", show_default=False)],
) -> None:
    """Print each dataset's content digest (SHA-256 over every stored shard array and every index column
    but solver times, attempts and shard file names): two runs of the same job hold the same samples
    exactly when their digests agree.

    One line each: DIGEST  SAMPLES  DISTINCT-IDS  URL; a URL that holds no readable dataset is one error
    line, the others are still digested, and the command then exits 2.
    """
    from storage.readers import dataset_digest

    refused: typer.Exit | None = None
    for url in urls:
        try:
            with user_errors(url):
                found = dataset_digest(url, dataset_options(url))
        except typer.Exit as exit_:  # user_errors printed the line; go on with the rest
            refused = exit_
            continue
        typer.echo(f"{found.sha256}  {found.samples}  {found.distinct_ids}  {url}")
    if refused is not None:
        raise refused


UNCOVERED_KIND = "uncovered"
"""`storage.validate`'s kind for a label that leaves keys of its U uncovered."""


def validate(
    url: UrlArgument,
    every: Annotated[
        bool, typer.Option("--all", help="Check every label with the solver (default: a seeded sample per shard).")
    ] = False,
    seed: Annotated[int, typer.Option("--seed", min=0, help="Seeds which rows are sampled without --all.")] = 0,
    sample: Annotated[
        float | None,
        typer.Option(
            "--sample",
            help="Read and check the shards of this share of the tasks only (0.01: 1 %, seeded by --seed); "
            "every record and the index are still checked whole.",
        ),
    ] = None,
    workers: Annotated[
        int,
        typer.Option("--workers", min=1, help="Chunks of tasks checked side by side on a local Ray (default 1: here)."),
    ] = 1,
    address: Annotated[
        str | None, typer.Option("--address", help="Check on this Ray cluster (its workers reach the store).")
    ] = None,
) -> None:
    """Check structure, index, records and labels (cover, minimum, lexicographic); exit 0 only when all holds.

    Warnings (leftover temporary files, stale failure records) are printed but do not fail it.
    """
    from datagen.engine.parallel import run_each
    from datagen.inspection.validation import check_chunk, task_chunks
    from storage.checks import check_dataset, plan_validation

    with user_errors(url):
        options = dataset_options(url)
        plan = plan_validation(url, options, sample, seed)
        found = check_dataset(plan)
        storage_problems = list(found.problems)
        labels: list[LabelProblem] = []
        checked = 0
        if plan.info is not None:
            calls = task_chunks(plan, url, options, every, seed)
            done = 0
            chunks = []
            with progress_bar() as bar:
                shards = bar.add_task("shards: structure, coverage, labels", total=len(plan.chosen))
                for findings in run_each(check_chunk, calls, workers, address):
                    chunks.append(findings)
                    done += findings.tasks
                    bar.update(shards, completed=done)
            for findings in sorted(chunks, key=lambda f: f.number):  # the tasks' order, whoever ran them
                storage_problems.extend(findings.problems)
                labels.extend(findings.labels)
                checked += findings.checked
        label_lines = _new_label_lines(storage_problems, labels)
        problems = lines(storage_problems) + label_lines
        for line in problems:
            say(line)
        for line in found.warnings:
            say(f"warning: {line}")
        scope = "every label" if every else "a sample of labels"
        share = ""
        if found.tasks_checked < found.tasks_total:
            percent = 100 * found.tasks_checked / found.tasks_total
            share = f"; shards of {found.tasks_checked} of {found.tasks_total} tasks checked ({percent:.1f} %)"
        warned = f", {plural(len(found.warnings), 'warning')} (harmless leftovers)" if found.warnings else ""
        if problems:
            say(
                f"{plural(len(problems), 'problem')} ({checked} labels checked with the solver, {scope}{share}){warned}"
            )
            say(fix_line(url, storage_problems, bool(label_lines)))
            raise typer.Exit(1)
        sound = f"{plural(found.tasks_total, 'task')} sound"
        if share:  # a sample: say what was read, not more
            sound = f"{found.tasks_checked} of {plural(found.tasks_total, 'task')} read and sound, every record sound"
        say(f"ok: {sound}, {checked} labels checked with the solver ({scope}{share}){warned}")


def fix_line(url: str, problems: list[Problem], labels: bool) -> str:
    """What mends what validate found: `datagen shards repair` for a damaged task or index (from the
    problems' records), a new dataset when ``dataset.json`` itself is damaged."""
    mends = {problem.mend for problem in problems}
    if any(problem.mend == Mend.NONE and not problem.file for problem in problems):
        return f"fix: check the URL: {url} holds no datagen dataset"
    if Mend.NONE in mends:
        return (
            f"fix: {url}'s dataset.json is damaged and nothing in the dataset can restore it: restore it from a "
            "copy, or re-submit the objects to a new --out"
        )
    fixes = []
    if mends:
        tasks = len({problem.task for problem in problems if problem.mend == Mend.TASK})
        what = (
            f"re-runs the {plural(tasks, 'damaged task')} from the ledger that made them" if tasks else "finalises it"
        )
        fixes.append(f"datagen shards repair {url} ({what}; where the job was submitted, or give --home)")
    if labels:  # labels the solver disagrees with, in sound shards: labelled again from the stored sets
        fixes.append(f"datagen shards relabel {url} --out NEW_URL (labels every case again from its stored sets)")
    return "fix: " + "; then ".join(fixes)


def _new_label_lines(storage_problems: list[Problem], labels: list[LabelProblem]) -> list[str]:
    """The label checker's lines, minus those storage already reported for the same shard or row (from
    the records: the shard a problem is in, the sample whose label leaves keys of U uncovered)."""
    from datagen.inspection.label_check import UNCOVERED, UNREADABLE

    damaged_shards = {p.file for p in storage_problems if not p.place}
    uncovered = {(p.file, p.place) for p in storage_problems if p.kind == UNCOVERED_KIND}
    lines = []
    for problem in labels:
        if problem.kind == UNREADABLE and problem.shard in damaged_shards:
            continue
        if problem.kind == UNCOVERED and (problem.shard, f"row {problem.row}") in uncovered:
            continue
        lines.append(problem.line)
    return lines


def relabel(
    url: UrlArgument,
    out: Annotated[
        str,
        typer.Option(
            "--out",
            help="Where the new dataset goes: an empty place, or the --out of a stopped relabel of the same "
            "settings (finished, its committed tasks kept).",
        ),
    ],
    alpha: Annotated[
        int | None, typer.Option("--alpha", min=1, help="The new alpha (views a key needs to enter P_full).")
    ] = None,
    tie_break: Annotated[
        str | None,
        typer.Option("--tie-break", help="Which minimum cover is the label: 'index' or 'coverage' (config docs)."),
    ] = None,
    objective: Annotated[
        str | None,
        typer.Option(
            "--objective",
            help="What a label is: 'cover' (the paper's), 'max_coverage' (--budget) or 'partial_cover' (--tau).",
        ),
    ] = None,
    budget: Annotated[
        int | None, typer.Option("--budget", min=1, help="max_coverage: most views a label holds beyond the input.")
    ] = None,
    tau: Annotated[
        float | None,
        typer.Option("--tau", help="partial_cover: share of what all views see that input and label must see."),
    ] = None,
    workers: Annotated[
        int,
        typer.Option("--workers", min=1, help="Tasks relabelled side by side on a local Ray (default 1: here)."),
    ] = 1,
    address: Annotated[
        str | None, typer.Option("--address", help="Relabel on this Ray cluster (its workers reach the store).")
    ] = None,
) -> None:
    """A new dataset: the same samples labelled for another alpha, tie-break or objective from the stored sets (no
    re-imaging)."""
    from datagen.engine.relabel import RelabelProgress, relabel_dataset

    with user_errors(url):
        with progress_bar() as bar:
            task = bar.add_task("relabelling tasks", total=None)

            def advance(state: RelabelProgress) -> None:
                bar.update(task, completed=state.tasks_done, total=state.tasks_total)

            options = dataset_options(url) or dataset_options(out)
            summary = relabel_dataset(
                url,
                alpha,
                out,
                storage_options=options,
                progress=advance,
                tie_break=tie_break,
                objective=objective,
                budget=budget,
                tau=tau,
                workers=workers,
                address=address,
            )
        say(
            f"relabelled {plural(summary.samples, 'sample')} of {plural(summary.tasks, 'task')} for "
            f"{summary.objective}, alpha "
            f"{summary.alpha}, tie-break {summary.tie_break} (source: {summary.source_objective}, alpha "
            f"{summary.source_alpha}, tie-break {summary.source_tie_break})"
        )
        say(f"{summary.seconds:.1f} s, {summary.labels_per_second:.1f} labels/s")
        if summary.kept:
            say(f"kept {plural(summary.kept, 'task')} a stopped relabel into {summary.out} had committed")
        if summary.dropped_empty or summary.failed_cases:
            say(f"{summary.dropped_empty} empty labels dropped, {summary.failed_cases} cases not proven optimal")
        say(f"carried over {summary.failures} failure records")
        say(f"dataset: {summary.out}")
        say(f"config hash: {summary.config_hash}")
