"""`datagen shards ls | show | stats` through the CLI, on an engine-written dataset (local) and on its
copy in fsspec's memory filesystem. Expected values are recomputed here from the shards themselves
(masks, key sets, commit and failure records), not from the index columns the commands summarise."""

from __future__ import annotations

import io
import json
import re
import shutil
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib import colormaps
from PIL import Image
from support import storage as fx
from support.shards import EngineDataset, engine_dataset  # noqa: F401
from typer.testing import CliRunner

from datagen.cli import common
from datagen.cli.main import app
from datagen.cli.shards_view import format_bytes
from datagen.inspection import plots
from datagen.inspection.listing import COMMITTED, FAILED, list_tasks
from storage import open_dataset
from storage.readers import Dataset

WIDTH = 80
QUANTILES = ("p0", "p5", "p50", "p95", "p100")
TASK_ROW = re.compile(r"^\s*([0-9a-f]{16}-r\d+)\s")


@pytest.fixture(params=["url", "memory_url"])
def url(request: pytest.FixtureRequest, engine_dataset: EngineDataset) -> str:  # noqa: F811
    return str(getattr(engine_dataset, request.param))


@pytest.fixture
def runner(monkeypatch: pytest.MonkeyPatch) -> CliRunner:
    """Both consoles render as on an 80-column terminal."""
    monkeypatch.setattr(common.console, "_width", WIDTH)
    monkeypatch.setattr(common.error_console, "_width", WIDTH)
    return CliRunner()


def invoke(runner: CliRunner, *args: str) -> Any:
    result = runner.invoke(app, ["shards", *args])
    assert result.exit_code == 0, (result.output, result.exception)
    return result


def assert_fits_80_columns(text: str) -> None:
    lines = text.splitlines()
    # only `ls`'s closing lines (one per failed task, with its full message) may wrap
    assert lines and max(len(line) for line in lines if not line.startswith("failed ")) <= WIDTH, text
    assert "…" not in text, text  # nothing truncated


def assert_whole_lines(text: str) -> None:
    """Off a terminal every table is tab-separated lines: no cell wrapped onto a line of its own, none
    cut (issue 42: ids, names and hashes are copied from a pipe whole)."""
    lines = text.splitlines()
    assert lines and "…" not in text, text
    assert not any(line.startswith("\t") for line in lines), text  # a wrapped cell's rest: an empty first cell
    assert not any("│" in line or "─" in line for line in lines), text  # no box drawing, no rich table


def assert_one_error_line(result: Any, fragment: str) -> None:
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and fragment in lines[0], result.stderr


# ---------------------------------------------------------------------------------------------------------
# what the dataset holds, computed without the index summaries
# ---------------------------------------------------------------------------------------------------------


def local_records(engine: EngineDataset, folder: str) -> list[dict[str, Any]]:
    root = Path(engine.url) / folder
    return [json.loads(path.read_text()) for path in sorted(root.glob("*.json"))]


def bytes_under(root: Path, relative: str) -> int:
    path = root / relative
    if path.is_file():
        return path.stat().st_size
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def task_rows(dataset: Dataset) -> dict[str, list[int]]:
    rows: dict[str, list[int]] = {}
    for i, task_id in enumerate(dataset.index.column("task_id").to_pylist()):
        rows.setdefault(task_id, []).append(i)
    return rows


def expected_tasks(engine: EngineDataset, dataset: Dataset) -> dict[str, dict[str, Any]]:
    """Per task: samples (commit record), points (stored key sets), bytes (files on disk), state."""
    by_task = task_rows(dataset)
    expected = {}
    for commit in local_records(engine, "commits"):
        task_id = commit["task_id"]
        expected[task_id] = {
            "samples": commit["num_samples"],
            "points": sum(len(dataset.keys(i, "points")) for i in by_task[task_id]),
            "bytes": bytes_under(Path(engine.url), commit["shard"])
            + bytes_under(Path(engine.url), commit["index_fragment"]),
            "state": COMMITTED,
        }
    for failure in local_records(engine, "failures"):
        expected[failure["task_id"]] = {"state": FAILED, "message": failure["message"], "object": "broken"}
    return expected


def all_masks(dataset: Dataset) -> tuple[np.ndarray, np.ndarray]:
    pairs = np.array([dataset.masks(i) for i in range(len(dataset))], dtype=np.uint64)
    return pairs[:, 0], pairs[:, 1]


def popcount(masks: np.ndarray) -> np.ndarray:
    return np.bitwise_count(masks).astype(np.int64)


# ---------------------------------------------------------------------------------------------------------
# ls
# ---------------------------------------------------------------------------------------------------------


def test_ls_lists_committed_and_failed_tasks(runner: CliRunner, url: str, engine_dataset: EngineDataset) -> None:  # noqa: F811
    dataset = open_dataset(url)
    expected = expected_tasks(engine_dataset, dataset)
    assert len(expected) == engine_dataset.committed_tasks + engine_dataset.failed_tasks == 8

    result = invoke(runner, "ls", url)
    assert_fits_80_columns(result.stdout)
    rows = {}
    order = []
    for line in result.stdout.splitlines():
        match = TASK_ROW.match(line)
        if match:
            tokens = line.split()
            rows[tokens[0]] = {"object": tokens[1], "rotation": tokens[2], "samples": tokens[3], "points": tokens[4]}
            rows[tokens[0]] |= {"size": " ".join(tokens[5:-1]), "state": tokens[-1]}
            order.append((tokens[1], int(tokens[2])))
    assert sorted(rows) == sorted(expected)
    assert order == sorted(order)  # by object, then rotation
    for task_id, want in expected.items():
        got = rows[task_id]
        assert got["state"] == want["state"], task_id
        assert got["rotation"] == task_id.rsplit("-r", 1)[1]
        if want["state"] == COMMITTED:
            assert int(got["samples"]) == want["samples"] == len(task_rows(dataset)[task_id])
            assert int(got["points"]) == want["points"]
            assert got["size"] == format_bytes(want["bytes"])
        else:
            assert got["object"] == want["object"]
            assert (got["samples"], got["points"], got["size"]) == ("-", "-", "-")
            assert f"failed {task_id} (" in result.stdout and want["message"] in result.stdout
    samples = sum(w.get("samples", 0) for w in expected.values())
    assert f"6 committed ({samples} samples, " in result.stdout and ", 2 failed" in result.stdout


def test_ls_json_is_what_a_script_reads(runner: CliRunner, url: str, engine_dataset: EngineDataset) -> None:  # noqa: F811
    """``ls --json``: every task with its counts, bytes, state and failure, then the totals."""
    import json

    dataset = open_dataset(url)
    expected = expected_tasks(engine_dataset, dataset)
    found = json.loads(invoke(runner, "ls", url, "--json").stdout)
    tasks = {task["task_id"]: task for task in found["tasks"]}
    assert sorted(tasks) == sorted(expected)
    for task_id, want in expected.items():
        got = tasks[task_id]
        assert got["state"] == want["state"]
        if want["state"] == COMMITTED:
            assert (got["samples"], got["points"], got["bytes_on_disk"]) == (
                want["samples"],
                want["points"],
                want["bytes"],
            )
        else:
            assert want["message"] in got["message"]
    assert (found["committed"], found["failed"]) == (6, 2)
    assert found["samples"] == sum(w.get("samples", 0) for w in expected.values()) == len(dataset)


def test_listing_counts_exact_bytes_and_skips_orphans(url: str, engine_dataset: EngineDataset) -> None:  # noqa: F811
    dataset = open_dataset(url)
    expected = expected_tasks(engine_dataset, dataset)
    listed = list_tasks(dataset)
    assert [row.sort_key() for row in listed] == sorted(row.sort_key() for row in listed)
    for row in listed:
        if row.state == COMMITTED:
            assert row.bytes_on_disk == expected[row.task_id]["bytes"] > 0
            assert (row.samples, row.points) == (expected[row.task_id]["samples"], expected[row.task_id]["points"])
        else:
            assert (row.bytes_on_disk, row.message) == (0, expected[row.task_id]["message"])
    # bytes of an attempt no commit names (a crashed attempt) are not the task's
    if url == engine_dataset.url:
        committed = next(r for r in listed if r.state == COMMITTED)
        orphan = Path(url) / "shards" / committed.task_id / "a9-crashed.parquet"
        orphan.write_bytes(b"x" * 4096)
        try:
            again = {r.task_id: r.bytes_on_disk for r in list_tasks(dataset)}
        finally:
            orphan.unlink()
        assert again[committed.task_id] == committed.bytes_on_disk


# ---------------------------------------------------------------------------------------------------------
# show
# ---------------------------------------------------------------------------------------------------------


def field(output: str, name: str) -> str:
    for line in output.splitlines():
        if line.startswith((name + " ", name + "\t")):
            return line[len(name) :].strip()
    raise AssertionError(f"no {name!r} line in:\n{output}")


def listed_views(text: str) -> list[int]:
    views = text.split("(")[0].split()
    return [] if views == ["none"] else [int(v) for v in views]


def chosen_rows(dataset: Dataset) -> list[int]:
    """The first and last samples, and one with at least two input views and a non-empty label."""
    cases, labels = all_masks(dataset)
    rich = np.flatnonzero((popcount(cases) >= 2) & (labels != 0))
    return [0, int(rich[0]), len(dataset) - 1]


def test_show_prints_the_stored_views_and_counts(runner: CliRunner, url: str) -> None:
    dataset = open_dataset(url)
    for row in chosen_rows(dataset):
        view_state, label = dataset.masks(row)
        sample_id = dataset.index.column("sample_id")[row].as_py()
        result = invoke(runner, "show", url, str(row))
        assert_whole_lines(result.stdout)
        out = result.stdout
        assert field(out, "sample").startswith(f"{sample_id} (row {row})")
        inputs, outputs = listed_views(field(out, "input views")), listed_views(field(out, "label views"))
        assert inputs == [v for v in range(dataset.num_views) if view_state >> v & 1]
        assert outputs == [v for v in range(dataset.num_views) if label >> v & 1]
        strip = field(out, "views").split()[0]
        assert len(strip) == dataset.num_views
        assert [i for i, c in enumerate(strip) if c == "I"] == inputs
        assert [i for i, c in enumerate(strip) if c == "L"] == outputs
        points = re.findall(r"\d+", field(out, "points"))
        assert [int(p) for p in points] == [len(dataset.keys(row, "points")), len(dataset.keys(row, "observed"))]
        meta = dataset.index.slice(row, 1).to_pylist()[0]
        assert f"config\t{meta['config_hash'][:16]}, schema" in out  # the hash whole, on its field's line
        assert field(out, "solver").startswith(f"{meta['solver_status']}, proof {meta['solver_proof']}")
        assert field(out, "object").startswith(meta["object_name"])
        by_id = invoke(runner, "show", url, sample_id)
        assert by_id.stdout == out


def test_show_errors_are_one_line(runner: CliRunner, url: str, tmp_path: Path) -> None:
    count = len(open_dataset(url))
    assert_one_error_line(runner.invoke(app, ["shards", "show", url, str(count)]), "out of range")
    assert_one_error_line(runner.invoke(app, ["shards", "show", url, "no-such-sample"]), "no sample 'no-such-sample'")
    missing = str(tmp_path / "nothing")
    for command in (["show", missing, "0"], ["ls", missing], ["stats", missing]):
        assert_one_error_line(runner.invoke(app, ["shards", *command]), "dataset.json")
    unwritable = tmp_path / "no-folder" / "sample.png"
    assert_one_error_line(runner.invoke(app, ["shards", "show", url, "0", "--png", str(unwritable)]), "cannot write")


def test_a_damaged_dataset_is_one_error_line_naming_the_file(
    runner: CliRunner,
    engine_dataset: EngineDataset,  # noqa: F811
    tmp_path: Path,
) -> None:
    """A deleted chunk file of ``points_keys``: ``show`` read zeros before; ``ls`` and ``stats`` read
    a truncated index.parquet with pyarrow's bare ArrowInvalid."""
    damaged = Path(shutil.copytree(engine_dataset.url, tmp_path / "chunk"))
    shard = json.loads(sorted((damaged / "commits").glob("*.json"))[0].read_text())["shard"]
    fx.zip_without(damaged / shard, "points_keys/c/0/0")
    result = runner.invoke(app, ["shards", "show", str(damaged), "0"])
    assert_one_error_line(result, f"{shard}: missing chunk files: points_keys")
    assert f"datagen shards validate {damaged}" in result.stderr
    truncated = Path(shutil.copytree(engine_dataset.url, tmp_path / "index"))
    index = fx.samples_table(truncated)
    index.write_bytes(index.read_bytes()[: index.stat().st_size // 2])
    for command in ("ls", "stats"):
        result = runner.invoke(app, ["shards", command, str(truncated)])
        assert_one_error_line(result, f"{truncated}: {index.relative_to(truncated)}: unreadable Parquet")
        assert f"datagen shards validate {truncated}" in result.stderr


# ---------------------------------------------------------------------------------------------------------
# stats
# ---------------------------------------------------------------------------------------------------------


def expected_stats(engine: EngineDataset, dataset: Dataset) -> dict[str, Any]:
    cases, labels = all_masks(dataset)
    case_sizes, label_sizes = popcount(cases), popcount(labels)
    histogram: dict[str, dict[str, int]] = {}
    for (case_size, label_size), count in sorted(Counter(zip(case_sizes, label_sizes, strict=True)).items()):
        histogram.setdefault(str(case_size), {})[str(label_size)] = count
    per_object: Counter[str] = Counter()
    per_task = []
    for commit in local_records(engine, "commits"):
        attributes = dataset.shard(commit["shard"]).attributes
        per_object[attributes.object_name] += commit["num_samples"]
        per_task.append({"object": attributes.object_name, "rotation": attributes.rotation})
        per_task[-1]["samples"] = commit["num_samples"]
    points = np.array([len(dataset.keys(i, "points")) for i in range(len(dataset))], dtype=np.float64)
    seconds = dataset.index.column("solver_seconds").to_numpy()
    return {
        "samples": len(cases),
        "committed_tasks": engine.committed_tasks,
        "failed_tasks": engine.failed_tasks,
        "samples_per_object": dict(sorted(per_object.items())),
        "samples_per_task": sorted(per_task, key=lambda t: (t["object"], t["rotation"])),
        "cases_per_case_size": {str(k): v for k, v in sorted(Counter(case_sizes.tolist()).items())},
        "label_sizes": histogram,
        "empty_labels": int(np.count_nonzero(labels == 0)),
        "points_percentiles": dict(zip(QUANTILES, np.percentile(points, [0, 5, 50, 95, 100]), strict=True)),
        "solver_seconds_percentiles": dict(zip(QUANTILES, np.percentile(seconds, [0, 5, 50, 95, 100]), strict=True)),
        "failed": sorted(
            ({"task_id": f["task_id"], "object": f["object_name"], "message": f["message"]} for f in failures(engine)),
            key=lambda f: f["task_id"],
        ),
    }


def failures(engine: EngineDataset) -> list[dict[str, Any]]:
    return local_records(engine, "failures")


def test_stats_json_agrees_with_the_shards(runner: CliRunner, url: str, engine_dataset: EngineDataset) -> None:  # noqa: F811
    dataset = open_dataset(url)
    want = expected_stats(engine_dataset, dataset)
    got = json.loads(invoke(runner, "stats", url, "--json").stdout)
    assert got["url"] == url
    for key in ("samples", "committed_tasks", "failed_tasks", "samples_per_object", "samples_per_task"):
        assert got[key] == want[key], key
    for key in ("cases_per_case_size", "label_sizes", "empty_labels"):
        assert got[key] == want[key], key
    assert sum(got["cases_per_case_size"].values()) == len(dataset) and want["empty_labels"] > 0
    for key in ("points_percentiles", "solver_seconds_percentiles"):
        assert got[key].keys() == want[key].keys()
        np.testing.assert_allclose([got[key][q] for q in want[key]], list(want[key].values()), rtol=1e-12)
    assert [{k: f[k] for k in ("task_id", "object", "message")} for f in got["failed"]] == want["failed"]
    assert len(want["failed"]) == 2
    proofs = Counter(dataset.index.column("solver_proof").to_pylist())
    assert got["solver_proofs"] == dict(sorted(proofs.items()))


def test_stats_tables_show_the_same_numbers(runner: CliRunner, url: str, engine_dataset: EngineDataset) -> None:  # noqa: F811
    dataset = open_dataset(url)
    want = expected_stats(engine_dataset, dataset)
    out = invoke(runner, "stats", url).stdout
    assert_whole_lines(out)
    assert out.startswith(
        f"{want['samples']} samples in 6 committed tasks, 2 failed; {want['empty_labels']} empty labels"
    )
    section = out.split("cases per case size")[1].split("percentiles")[0]
    table = {}
    for line in section.splitlines():
        tokens = line.split()
        if tokens and tokens[0].isdigit():
            table[tokens[0]] = (int(tokens[1]), int(tokens[2]), dict(t.split(":") for t in tokens[3:]))
    assert table.keys() == want["cases_per_case_size"].keys()
    for size, (cases, empty, labels) in table.items():
        assert cases == want["cases_per_case_size"][size]
        assert labels == {k: str(v) for k, v in want["label_sizes"][size].items()}
        assert empty == want["label_sizes"][size].get("0", 0)
    for name, count in want["samples_per_object"].items():
        rotations = "  ".join(
            f"{t['rotation']}:{t['samples']}" for t in want["samples_per_task"] if t["object"] == name
        )
        assert re.search(rf"^\s*{name}\s+{count}\s+{rotations}\s*$", out, re.MULTILINE), name
    points_line = next(line for line in out.splitlines() if line.strip().startswith("points"))
    assert points_line.split()[1:] == [f"{v:.0f}" for v in want["points_percentiles"].values()]
    for failure in want["failed"]:
        assert failure["task_id"] in out
    assert "failed tasks" in out and "not a readable mesh" in out


# ---------------------------------------------------------------------------------------------------------
# pictures
# ---------------------------------------------------------------------------------------------------------


def load_png(data: bytes) -> np.ndarray:
    image = Image.open(io.BytesIO(data))
    assert image.format == "PNG"
    return np.asarray(image.convert("RGB"), dtype=np.int16)


def colour_mask(pixels: np.ndarray, colour: str, tolerance: int = 0) -> np.ndarray:
    return (np.abs(pixels - np.array(plots.rgb(colour))) <= tolerance).all(axis=-1)


def assert_not_blank(pixels: np.ndarray) -> None:
    assert pixels.std() > 20
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 200


def test_show_png_draws_clouds_views_and_legend(runner: CliRunner, url: str, tmp_path: Path) -> None:
    dataset = open_dataset(url)
    row = chosen_rows(dataset)[1]
    out = tmp_path / "sample.png"
    result = invoke(runner, "show", url, str(row), "--png", str(out))
    assert f"wrote {out}" in result.stdout
    pixels = load_png(out.read_bytes())
    height, width = pixels.shape[:2]
    assert (width, height) == (plots.SAMPLE_FIGSIZE[0] * plots.DPI, plots.SAMPLE_FIGSIZE[1] * plots.DPI) == (1200, 500)
    assert_not_blank(pixels)

    legend = colour_mask(pixels, plots.LEGEND_FACE_COLOUR)
    ys, xs = np.nonzero(legend)
    assert legend.sum() > 5000 and ys.min() > 0.8 * height  # a legend box along the bottom
    box = pixels[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1]
    assert ((box < 80).all(axis=-1)).sum() > 300  # its text
    for colour in (plots.INPUT_VIEW_COLOUR, plots.LABEL_VIEW_COLOUR, plots.OBSERVED_COLOUR, plots.REFINED_COLOUR):
        assert colour_mask(box, colour).sum() > 50, colour  # its markers

    above = pixels[: ys.min()]
    views = above[:, 2 * width // 3 :]
    assert colour_mask(views, plots.INPUT_VIEW_COLOUR).sum() > 60  # at least one whole input-view marker
    assert colour_mask(views, plots.LABEL_VIEW_COLOUR).sum() > 60
    assert colour_mask(views, plots.OTHER_VIEW_COLOUR).sum() > 100
    assert colour_mask(above[:, : width // 3], plots.OBSERVED_COLOUR, tolerance=8).sum() > 300  # observed cloud
    assert colour_mask(above[:, width // 3 : 2 * width // 3], plots.REFINED_COLOUR, tolerance=8).sum() > 300


def test_stats_png_draws_the_histograms(runner: CliRunner, url: str, tmp_path: Path) -> None:
    out = tmp_path / "stats.png"
    result = invoke(runner, "stats", url, "--json", "--png", str(out))
    assert json.loads(result.stdout)["samples"] == len(open_dataset(url))  # --png keeps stdout pure JSON
    pixels = load_png(out.read_bytes())
    height, width = pixels.shape[:2]
    assert (width, height) == (plots.STATS_FIGSIZE[0] * plots.DPI, plots.STATS_FIGSIZE[1] * plots.DPI) == (1200, 450)
    assert_not_blank(pixels)
    third = width // 3
    assert colour_mask(pixels[:, third : 2 * third], plots.POINTS_HIST_COLOUR).sum() > 1000
    assert colour_mask(pixels[:, 2 * third :], plots.SOLVER_HIST_COLOUR).sum() > 1000
    top = colormaps[plots.LABEL_HISTOGRAM_CMAP](1.0)[:3]
    top_hex = "#" + "".join(f"{round(c * 255):02x}" for c in top)
    assert colour_mask(pixels[:, :third], top_hex, tolerance=1).sum() > 200  # the most frequent cell


def test_format_bytes_uses_binary_units() -> None:
    assert [format_bytes(n) for n in (0, 812, 10_854, 1_310_720, 5 * 1024**4)] == [
        "0 B",
        "812 B",
        "10.6 KiB",
        "1.25 MiB",
        "5 TiB",
    ]
