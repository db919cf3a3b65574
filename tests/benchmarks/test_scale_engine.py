"""benchmarks/scale/engine.py's pieces on tiny inputs: a child measured by the kernel (CPU, peak
memory, a deadline that stops it), growth stated as ratios and a log-log slope, the cache a stopped
run goes on from, the ShapeNet-shaped tree that `objects scan` lists, the first lines of a listing,
and the report's tables (the large runs are the benchmark, never a test)."""

from __future__ import annotations

import sys
from pathlib import Path
from types import ModuleType

import pytest
from support.benchmarks import load_benchmark

from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.scan import scan_meshes


@pytest.fixture(scope="module")
def measure() -> ModuleType:
    return load_benchmark("scale.measure")


@pytest.fixture(scope="module")
def engine() -> ModuleType:
    return load_benchmark("scale.engine")


@pytest.fixture(scope="module")
def objects() -> ModuleType:
    return load_benchmark("scale.objects")


def test_a_child_is_measured_by_the_kernel(measure: ModuleType, tmp_path: Path) -> None:
    code = (
        "import json, sys, time\n"
        "block = bytearray(64 * 1024 * 1024)\n"
        "for i in range(0, len(block), 4096): block[i] = 1\n"
        "end = time.process_time() + 0.3\n"
        "while time.process_time() < end: pass\n"
        "print('hello'); json.dump({'said': 1}, open(sys.argv[1], 'w'))\n"
    )
    report = tmp_path / "report.json"
    measured = measure.run_measured(
        [sys.executable, "-c", code, str(report)], cwd=tmp_path, env={}, stdout=tmp_path / "out.log", report=report
    )
    assert measured.rc == 0 and not measured.stopped
    assert measured.cpu >= 0.3 and measured.wall >= measured.cpu * 0.5
    assert measured.peak_mb >= 64
    assert measured.extra == {"said": 1}
    assert (tmp_path / "out.log").read_text() == "hello\n"
    assert measure.Measurement.from_json(measured.to_json()) == measured


def test_a_deadline_stops_the_child_with_sigint(measure: ModuleType, tmp_path: Path) -> None:
    code = "import time\ntry:\n    time.sleep(60)\nexcept KeyboardInterrupt:\n    print('stopped')\n"
    measured = measure.run_measured(
        [sys.executable, "-c", code], cwd=tmp_path, env={}, stdout=tmp_path / "out.log", deadline=0.5
    )
    assert measured.stopped and measured.rc == 0 and measured.wall < 30
    assert (tmp_path / "out.log").read_text() == "stopped\n"


def test_a_deadline_first_asks_the_child_to_stop_its_own_way(measure: ModuleType, tmp_path: Path) -> None:
    flag = tmp_path / "cancelled"
    code = (
        f"import pathlib, time\nwhile not pathlib.Path({str(flag)!r}).exists():\n    time.sleep(0.05)\nprint('done')\n"
    )
    measured = measure.run_measured(
        [sys.executable, "-c", code],
        cwd=tmp_path,
        env={},
        stdout=tmp_path / "out.log",
        deadline=0.5,
        on_deadline=flag.touch,
    )
    assert measured.stopped and measured.rc == 0 and measured.wall < 30
    assert (tmp_path / "out.log").read_text() == "done\n"


def test_growth_is_ratios_and_a_log_log_slope(measure: ModuleType) -> None:
    assert measure.growth({1000: 1.0, 10000: 10.0, 100000: 100.0}) == "x10.0 x10.0 (slope 1.00)"
    assert measure.growth({1000: 1.0, 10000: 100.0}) == "x100.0 (slope 2.00)"
    assert measure.growth({1000: 2.0, 10000: 2.0}) == "x1.0 (slope 0.00)"
    assert measure.growth({1000: 2.0}) == ""


def test_the_cache_keeps_what_was_measured(measure: ModuleType, tmp_path: Path) -> None:
    cache = measure.Cache(tmp_path / "cache.json")
    cache.put("engine|after|1000", {"a": 1})
    assert measure.Cache(tmp_path / "cache.json").get("engine|after|1000") == {"a": 1}
    assert cache.get("missing") is None


def test_the_shapenet_shaped_tree_is_listed_by_scan(objects: ModuleType, tmp_path: Path) -> None:
    root = objects.make_tree(tmp_path / "tree", 60)
    result = scan_meshes(root)
    assert len(result.meshes) == 60 and len(result.categories) == objects.SYNSETS
    assert result.skipped == () and result.companions == 120
    assert all(m.path.name == "model_normalized.obj" and m.path.parts[-2] == "models" for m in result.meshes)
    assert objects.make_tree(root, 60) == root  # made once


def test_first_lines_make_absolute_paths(objects: ModuleType, tmp_path: Path) -> None:
    (tmp_path / "a.obj").write_text("v 0 0 0\n")
    (tmp_path / "b.obj").write_text("v 1 0 0\n")
    listing = tmp_path / "objects.txt"
    listing.write_text("# header\na.obj name=a\n\nb.obj name=b\n")
    out = objects.first_lines(listing, 2, tmp_path / "sub" / "first.txt")
    assert out.read_text() == f"{tmp_path / 'a.obj'} name=a\n{tmp_path / 'b.obj'} name=b\n"
    assert [o.name for o in read_objects_file(out).objects] == ["a", "b"]
    with pytest.raises(RuntimeError):
        objects.first_lines(listing, 3, tmp_path / "more.txt")


def test_the_report_tables(engine: ModuleType, measure: ModuleType) -> None:
    def run(cpu: float, done: int, stopped: bool = False) -> object:
        extra = {
            "run_cpu_s": cpu,
            "run_wall_s": 2 * cpu,
            "peak_mb": 300.0,
            "rss_before_mb": 250.0,
            "ticks": done,
            "curve": [[0.1 * i, cpu * i / 10, done * i // 10] for i in range(11)],
            "counts": {"done": done},
        }
        return measure.Measurement(10.0, 1.0, 400.0, 0, stopped, extra)

    plain = measure.Measurement(1.5, 1.2, 190.0, 0)
    before = {1000: {"submit": plain, "run": run(10.0, 1000)}, 10000: {"submit": plain, "run": run(50.0, 500, True)}}
    after = {1000: {"submit": plain, "run": run(1.0, 1000)}, 10000: {"submit": plain, "run": run(10.0, 10000)}}
    results = {"before": before, "after": after}
    compared = engine.comparison(["before", "after"], engine.ENGINE_ROWS, results, "tasks")
    run_row = next(line for line in compared if line.startswith("| `resume JOB`: driver runs"))
    assert "10.00 -> 1.00 ms/task (x10)" in run_row and "100.00 -> 1.00 ms/task (x100)" in run_row
    lines = engine.per_task_table("before", before)
    assert lines[4].startswith("| 1k | 1,000 | 10.00 | 20.00 | 10.00 | 10.00 |")
    assert lines[5].startswith("| 10k | 500 (stopped at 100 s) | 100.00 |")
    table = engine.table("after", engine.ENGINE_ROWS, after, "tasks")
    submit_row = next(line for line in table if line.startswith("| `submit --detach`"))
    assert "1.20 / 1.50 / 190" in submit_row and "x1.0 (slope 0.00)" in submit_row
