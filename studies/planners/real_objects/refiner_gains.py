"""Do the next-view labels depend on the refiner? (issue 49): the same objects and rotations made with
POCO and with no refiner, compared sample by sample.

    python -m studies.planners.real_objects.refiner_gains WORK/real-train-poco-r1 WORK/real-train-none-r1 \\
        [--out studies/planners/real_objects/results/refiner-gains.md --replace]

docs/pipeline.md (section 8.1) says a view's gain counts ground-truth surface keys only, so the gains,
the best next view and the input cases themselves are the same whichever refiner made the dataset;
only the cover labels (which ask what the refined union covers) may differ. This reads both datasets'
samples by id and counts what agrees: the sample ids, the view states, ``view_gain``, ``best_view``
and the labels.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import numpy as np

from benchmarks.common import add_report_options, check_report
from storage import open_dataset
from storage.readers import load_memory
from studies.planners.runs import write_markdown


def compare(first_url: str, second_url: str) -> list[tuple[str, str]]:
    """(what, agreement) rows for two datasets of the same objects."""
    first = load_memory(first_url, covers=False)
    second = load_memory(second_url, covers=False)
    rows: list[tuple[str, str]] = [(first_url, f"{len(first)} samples"), (second_url, f"{len(second)} samples")]
    if len(first) != len(second):
        rows.append(("same samples", "no: the sample counts differ"))
        return rows
    ids_a = np.asarray(open_dataset(first_url).values("sample_id"))[first.rows]
    ids_b = np.asarray(open_dataset(second_url).values("sample_id"))[second.rows]
    order_a, order_b = np.argsort(ids_a), np.argsort(ids_b)
    same_ids = bool(np.array_equal(ids_a[order_a], ids_b[order_b]))
    rows.append(("same sample ids", "yes" if same_ids else "no"))
    if not same_ids:
        return rows
    for name, values_a, values_b in (
        ("view states", first.view_state, second.view_state),
        ("view_gain", first.fields["view_gain"], second.fields["view_gain"]),
        ("best_view", first.fields["best_view"], second.fields["best_view"]),
        ("cover labels", first.labels, second.labels),
    ):
        a, b = values_a[order_a], values_b[order_b]
        equal = np.all(a == b, axis=tuple(range(1, a.ndim))) if a.ndim > 1 else a == b
        rows.append((f"equal {name}", f"{int(equal.sum())} of {len(equal)} samples ({100 * equal.mean():.1f} %)"))
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first")
    parser.add_argument("second")
    add_report_options(parser)
    args = parser.parse_args(argv)
    check_report(parser, args.out, args.replace)
    rows = compare(args.first, args.second)
    for what, agreement in rows:
        print(f"{what}: {agreement}")
    if args.out:
        table = ["| what | agreement |", "|---|---|", *(f"| {what} | {agreement} |" for what, agreement in rows)]
        write_markdown(args.out, "studies.planners.real_objects.refiner_gains", argv, table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
