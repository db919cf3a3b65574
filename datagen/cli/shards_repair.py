"""``datagen shards repair``: the fix every damage message names. A plain function;
`datagen.cli.shards` registers it."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from datagen.cli.common import UrlArgument, plural, progress_bar, say, user_errors


def repair(
    url: UrlArgument,
    home: Annotated[
        Path | None, typer.Option("--home", help="The ledger of the job that made the dataset (default DATAGEN_HOME).")
    ] = None,
    address: Annotated[str | None, typer.Option("--address", help="Ray cluster address (default: local Ray).")] = None,
    workers: Annotated[int | None, typer.Option("--workers", min=1, help="Local Ray CPUs (default: all).")] = None,
) -> None:
    """Re-run exactly the damaged tasks (as `datagen shards validate` finds them) with the job's own
    config and objects, then finalise the index; a sound dataset is left as it is."""
    from datagen.engine.driver import JobProgress
    from datagen.engine.repair import repair_dataset
    from datagen.settings import RunSettings, default_home

    with user_errors(url):
        base = RunSettings()
        settings = RunSettings(
            home=home or default_home(), ray_address=address or base.ray_address, num_workers=workers
        )
        with progress_bar() as bar:
            task = bar.add_task("re-running damaged tasks", total=None)

            def advance(state: JobProgress) -> None:
                bar.update(task, completed=state.done + state.failed, total=state.total)

            summary = repair_dataset(url, settings, progress=advance)
        if summary.sound:
            say(f"nothing to repair: {url} is sound ({summary.samples} samples); nothing was changed")
            return
        for task_id, line in sorted(summary.repaired.items()):
            say(f"re-ran {task_id}: {line}")
        for problem in summary.index_problems:
            say(f"index finalised again: {problem.line}")
        say(
            f"repaired: {plural(len(summary.repaired), 'task')} re-run (jobs {', '.join(summary.jobs) or '-'}), "
            "index finalised"
        )
        say(f"ok: {url} is sound ({summary.samples} samples)")
