"""storage.export.export_air and ``datagen shards export``: the authors' text layout (docs/authors-code.md
section 7.2), checked file by file against the pipeline's own samples, and read back by a mini reader that
follows AIR's COSC_Dataset and train.py line for line in what they read; their recall is computed on
what it returns."""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import pytest
import typer
from support.torch_data import (
    SMALL_OBJECTS,
    Built,
    bits,
    build_dataset,
    cached_dataset,
    dataset_info,
    expected_of,
    objects_file,
)
from typer.testing import CliRunner

from datagen.cli import common
from datagen.cli.shards import shards_app
from datagen.engine.shard_payload import task_payload
from datagen.pipeline.keys import pack_keys
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.refine import make_refiner
from datagen.pipeline.task import run_task
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig, ViewSpaceConfig
from storage import StorageError, open_dataset
from storage.dataset import finalise, init_dataset, write_task
from storage.export import (
    EMPTY_LABEL,
    NO_POINTS,
    PROVENANCE_JSON,
    PROVENANCE_MD,
    ROOT_FILES,
    Export,
    check_layout,
    export_air,
)
from storage.store import open_location

NUM_POINTS = 300
VAL = 0.34


@pytest.fixture(scope="session")
def small(tmp_path_factory: pytest.TempPathFactory) -> Built:
    return cached_dataset("small", tmp_path_factory.mktemp("export_small"))


@pytest.fixture(scope="session")
def exported(small: Built, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Export]:
    out = tmp_path_factory.mktemp("air_export") / "air"
    return out, export_air(small.url, out, num_points=NUM_POINTS, seed=7, val_fraction=VAL)


def files_under(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def exportable(built: Built) -> dict[str, object]:
    """The samples the export writes: a label to learn and points to learn it from."""
    return {sid: s for sid, s in built.samples.items() if s.label and len(s.points)}


def cosc_load(root: Path, split_file: str, num_views: int = 32) -> list[dict[str, object]]:
    """AIR's train.py ``build_dataset`` and COSC_Dataset, as they read (docs/authors-code.md section 7.2): object
    names are every line of the split file, stripped; under ``<root>/<obj>/`` every entry is a rotate
    dir, and in it every file whose name starts with 'cloud' is a sample; its companions are the whole
    path with 'cloud' replaced by 'state' and by 'ids'; float32 "x y z" rows, a float32 state,
    ``idx = loadtxt(ids, long); gt = zeros(32); gt[idx] = 1``. numpy's warning on an empty file is an
    error here (their loader would go on with an empty label)."""
    objs = []
    with open(os.path.join(str(root), split_file)) as f:
        for line in f:
            objs.append(line.strip())
    file_list = []
    for obj in objs:
        obj_path = os.path.join(str(root), obj)
        for rot in os.listdir(obj_path):
            rot_path = os.path.join(obj_path, rot)
            for f in os.listdir(rot_path):
                if f.startswith("cloud"):
                    file_list.append((obj, os.path.join(rot_path, f)))
    items = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for obj, path in file_list:
            cloud = np.loadtxt(path, dtype=np.float32)
            state = np.loadtxt(path.replace("cloud", "state"), dtype=np.float32)
            idx = np.loadtxt(path.replace("cloud", "ids"), dtype=np.int64)
            gt = np.zeros(num_views, dtype=np.float32)
            gt[idx] = 1
            items.append({"path": path, "object": obj, "cloud": cloud, "state": state, "gt": gt})
    return items


def authors_recall_precision(output: np.ndarray, label: np.ndarray, threshold: float = 0.5) -> tuple[float, float]:
    """train.py ``check_accuracy`` in numpy: per case correct / |label| and correct / predicted, summed,
    divided by the number of cases."""
    output = np.where(output >= threshold, 1, 0)
    correct1 = np.sum(np.logical_and(output == 1, label == 1), axis=1)
    wrong1 = np.sum(np.logical_and(output == 1, label == 0), axis=1)
    cnt1 = np.sum(label == 1, axis=1)
    recall = float(np.sum(correct1 / cnt1)) / len(label)
    precision = float(np.sum(correct1 / (correct1 + wrong1 + 1e-6))) / len(label)
    return recall, precision


def rotate_dir(rotation: int, rotations: int) -> str:
    """The authors' meaning: rotate_<k> is a yaw of 45 deg x k."""
    assert (rotation * 8) % rotations == 0
    return f"rotate_{rotation * 8 // rotations}"


def expected_by_file(url: str, built: Built) -> dict[str, object]:
    """'<obj>/rotate_<k>/cloud_<row>.txt' -> the pipeline's sample, for every exportable sample."""
    index = open_dataset(url).index
    keep = exportable(built)
    out = {}
    for sid, name, rotation, row in zip(
        index.column("sample_id").to_pylist(),
        index.column("object_name").to_pylist(),
        index.column("rotation").to_pylist(),
        index.column("row").to_pylist(),
        strict=True,
    ):
        if sid in keep:
            out[f"{name}/{rotate_dir(rotation, built.config.rotations)}/cloud_{row}.txt"] = built.samples[sid]
    return out


def point_keys(points: np.ndarray, config: GenerationConfig) -> np.ndarray:
    """Packed keys of exported points (voxel centres written with 6 decimals)."""
    scaled = points.astype(np.float64) / config.voxel_size + np.asarray(config.grid_offset)
    keys = np.floor(scaled).astype(np.int64)
    assert np.abs(scaled - keys - 0.5).max() < 1e-3  # at the centre of its voxel
    return pack_keys(keys)


def one_task_dataset(url: str, name: str, config: GenerationConfig, rotation: int = 0, edit=None) -> Built:  # type: ignore[no-untyped-def]
    """One built-in object at one rotation through the real pipeline; ``edit`` may change the
    TaskResult before it is written (to make samples the pipeline itself never makes)."""
    location = open_location(url)
    init_dataset(location, dataset_info(config))
    with tempfile.TemporaryDirectory() as folder:
        spec = read_objects_file(objects_file(Path(folder), [name])).objects[0]
    prepared = prepare_object(spec, config)
    result = run_task(prepared, rotation, config, build_view_space(config.view_space), make_refiner(config))
    if edit is not None:
        result = edit(result)
    write_task(location, task_payload(result, config), "a0")
    finalise(location)
    return Built(url=url, config=config, samples=expected_of(result))


# ---------------------------------------------------------------------------------------------------------
# layout and content
# ---------------------------------------------------------------------------------------------------------


def test_layout_has_one_cloud_state_ids_triple_per_sample(small: Built, exported: tuple[Path, Export]) -> None:
    out, summary = exported
    expected = expected_by_file(small.url, small)
    assert summary.written == len(exportable(small)) == len(expected)
    assert summary.samples == len(small.samples) == summary.written + len(summary.skipped)
    clouds = {str(p.relative_to(out)) for p in out.rglob("cloud_*.txt")}
    assert clouds == set(expected)
    every = {str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()}
    triples = {c.replace("cloud", k) for c in clouds for k in ("cloud", "state", "ids")}
    assert every == triples | set(ROOT_FILES)
    assert not [p for p in out.parent.iterdir() if p.name != out.name]  # no staging folder left behind


def test_files_hold_exactly_the_samples(small: Built, exported: tuple[Path, Export]) -> None:
    out, _ = exported
    for relative, sample in expected_by_file(small.url, small).items():
        cloud_path = out / relative
        lines = cloud_path.read_text().splitlines()
        assert len(lines) == NUM_POINTS
        assert all(len(line.split(" ")) == 3 for line in lines)
        points = np.loadtxt(cloud_path, dtype=np.float64)
        keys = point_keys(points, small.config)
        assert np.isin(keys, sample.points).all()
        if len(sample.points) >= NUM_POINTS:
            assert np.unique(keys).size == NUM_POINTS  # sampled without replacement
        state = (out / relative.replace("cloud", "state")).read_text().splitlines()
        assert state == [str(int(b)) for b in bits(sample.case, 32)]
        ids = [int(v) for v in (out / relative.replace("cloud", "ids")).read_text().split()]
        assert ids == sorted(ids)
        assert ids == [v for v in range(32) if sample.label >> v & 1]
        assert ids  # never an empty ids file


def test_split_files_partition_the_objects(small: Built, exported: tuple[Path, Export]) -> None:
    out, summary = exported
    train = (out / "train_split").read_text().splitlines()
    test = (out / "test_split").read_text().splitlines()
    names = {s.object_name for s in small.samples.values()}
    assert set(train) | set(test) == names == set(SMALL_OBJECTS)
    assert not set(train) & set(test)
    assert len(test) == round(VAL * len(names)) == 1
    assert len(train) == len(set(train)) and len(test) == len(set(test))
    assert (tuple(train), tuple(test)) == (summary.train_objects, summary.test_objects)
    # their train.py keeps every line, stripped: no blank line, and every name is a folder of rotate dirs
    for name in train + test:
        assert name and name == name.strip() and (out / name).is_dir()
        assert all(p.is_dir() for p in (out / name).iterdir())
    # the same objects as storage's own split of the dataset (nothing of these objects was all skipped)
    ds_train, ds_test = open_dataset(small.url).split(VAL, 7)
    assert set(train) == set(ds_train.index.column("object_name").to_pylist())
    assert set(test) == set(ds_test.index.column("object_name").to_pylist())


def test_authors_loader_reads_what_export_wrote(small: Built, exported: tuple[Path, Export]) -> None:
    out, summary = exported
    expected = expected_by_file(small.url, small)
    items = cosc_load(out, "train_split") + cosc_load(out, "test_split")
    assert len(items) == summary.written
    for item in items:
        relative = str(Path(str(item["path"])).relative_to(out))
        sample = expected[relative]
        cloud = item["cloud"]
        assert isinstance(cloud, np.ndarray) and cloud.shape == (NUM_POINTS, 3) and cloud.dtype == np.float32
        np.testing.assert_array_equal(item["state"], bits(sample.case, 32))
        np.testing.assert_array_equal(item["gt"], bits(sample.label, 32))
        assert item["object"] == sample.object_name


def test_authors_recall_on_the_export_is_defined(exported: tuple[Path, Export]) -> None:
    """Their check_accuracy over what their loader returns: no NaN, and an F1 above 0, so their
    best checkpoint is saved. An empty label (what the export skips) would make it NaN."""
    out, _ = exported
    items = cosc_load(out, "train_split")
    clouds = np.stack([np.asarray(i["cloud"]) for i in items])  # default collation: one cloud size
    states = np.stack([np.asarray(i["state"]) for i in items])
    labels = np.stack([np.asarray(i["gt"]) for i in items])
    assert clouds.shape == (len(items), NUM_POINTS, 3) and states.shape == labels.shape == (len(items), 32)
    assert labels.sum(axis=1).min() >= 1
    first_half = np.tile((np.arange(32) < 16).astype(np.float32), (len(items), 1))
    for prediction in (labels, np.ones_like(labels), first_half, states):
        recall, precision = authors_recall_precision(prediction, labels)
        assert np.isfinite(recall) and np.isfinite(precision)
        assert 0.0 <= recall <= 1.0 and 0.0 <= precision <= 1.0
    recall, precision = authors_recall_precision(labels, labels)
    assert recall == 1.0 and precision > 0.99
    assert 2 * precision * recall / (precision + recall + 1e-6) > 0  # train.py saves best_ckpt.pth
    with np.errstate(invalid="ignore"):
        empty = np.vstack([labels, np.zeros((1, 32), dtype=np.float32)])
        assert np.isnan(authors_recall_precision(empty, empty)[0])  # why empty labels are skipped


def test_export_is_deterministic_in_its_seed(small: Built, exported: tuple[Path, Export], tmp_path: Path) -> None:
    out, _ = exported
    again = tmp_path / "again"
    other = tmp_path / "other"
    export_air(small.url, again, num_points=NUM_POINTS, seed=7, val_fraction=VAL)
    export_air(small.url, other, num_points=NUM_POINTS, seed=8, val_fraction=VAL)
    first = files_under(out)
    assert files_under(again) == first  # provenance files included: they name no output path
    changed = files_under(other)
    assert changed.keys() == first.keys()
    assert any(changed[k] != first[k] for k in first if "cloud_" in k)
    assert all(changed[k] == first[k] for k in first if "state_" in k or "ids_" in k)


def test_progress_reports_every_sample(small: Built, tmp_path: Path) -> None:
    calls: list[tuple[int, int]] = []
    summary = export_air(small.url, tmp_path / "air", num_points=8, progress=lambda d, t: calls.append((d, t)))
    assert [d for d, _ in calls] == list(range(1, summary.samples + 1))
    assert {t for _, t in calls} == {summary.samples}


# ---------------------------------------------------------------------------------------------------------
# skipped samples, provenance
# ---------------------------------------------------------------------------------------------------------


def test_empty_label_and_zero_point_samples_are_skipped_and_reported(tmp_path: Path) -> None:
    config = GenerationConfig(rotations=8, refiner="none")
    emptied: list[str] = []

    def empty_one_cloud(result):  # type: ignore[no-untyped-def]
        target = next(s for s in result.samples if s.label)
        emptied.append(target.sample_id)
        samples = tuple(
            dataclasses.replace(s, points=np.empty(0, dtype=np.int64)) if s is target else s for s in result.samples
        )
        return dataclasses.replace(result, samples=samples)

    url = str(tmp_path / "odd")
    built = one_task_dataset(url, "capsule", config, edit=empty_one_cloud)
    empty_labels = {sid for sid, s in built.samples.items() if not s.label}
    assert empty_labels and len(emptied) == 1  # the capsule has cases that need no view

    out = tmp_path / "air"
    summary = export_air(url, out, num_points=64, val_fraction=0.0)
    assert summary.skipped == {**dict.fromkeys(empty_labels, EMPTY_LABEL), emptied[0]: NO_POINTS}
    assert (summary.skipped_empty_label, summary.skipped_no_points) == (len(empty_labels), 1)
    assert summary.written == len(built.samples) - len(empty_labels) - 1
    assert f"skipped {len(empty_labels)} samples with an empty label" in "\n".join(summary.lines)
    assert "skipped 1 samples with no points" in "\n".join(summary.lines)
    provenance = json.loads((out / PROVENANCE_JSON).read_text())
    assert provenance["skipped"]["empty_label"] == len(empty_labels)
    assert provenance["skipped"]["no_points"] == 1
    assert provenance["skipped"]["samples"] == dict(sorted(summary.skipped.items()))
    markdown = (out / PROVENANCE_MD).read_text()
    assert f"skipped {len(empty_labels)} samples with an empty label" in markdown
    assert "skipped 1 samples with no points" in markdown
    assert (out / "test_split").read_text() == ""  # val 0: no object held out, no (blank) line
    for path in out.rglob("*"):
        assert not path.is_file() or path.stat().st_size > 0 or path.name == "test_split", path
    items = cosc_load(out, "train_split")
    assert len(items) == summary.written
    labels = np.stack([np.asarray(i["gt"]) for i in items])
    assert np.isfinite(authors_recall_precision(labels, labels)).all()
    # rotations == 8: rotate_<r> as theirs
    assert [p.name for p in (out / "capsule").iterdir()] == ["rotate_0"]


def test_provenance_names_every_choice(small: Built, exported: tuple[Path, Export]) -> None:
    out, summary = exported
    provenance = json.loads((out / PROVENANCE_JSON).read_text())
    info = open_dataset(small.url).info
    assert provenance == summary.provenance
    dataset = provenance["dataset"]
    assert dataset["url"] == small.url and dataset["config_hash"] == info.config_hash
    assert dataset["alpha"] == small.config.alpha and dataset["refiner"] == ["test-shift"]
    assert dataset["samples"] == len(small.samples) and provenance["written"] == summary.written
    assert provenance["points"]["per_cloud"] == NUM_POINTS and provenance["points"]["seed"] == 7
    assert "seed" in provenance["points"]["rng"] and "sample_id" in provenance["points"]["rng"]
    assert provenance["frame"]["world_frame_recoverable"] is False
    assert provenance["rotations"]["folder_of_rotation"] == {"0": "rotate_0", "1": "rotate_4"}
    assert provenance["split"]["seed"] == 7 and provenance["split"]["val_fraction"] == VAL
    assert provenance["split"]["train_split"] == list(summary.train_objects)
    assert provenance["skipped"]["empty_label"] == summary.skipped_empty_label > 0
    lines = provenance["lines"]
    assert list(summary.lines[1:]) == lines[1:] and str(out) in summary.lines[0]
    topics = [line.split(":", 1)[0] for line in lines[3:]]
    assert topics == ["dataset", "points", "frame", "rotations", "views", "split", "provenance"]
    text = "\n".join(lines)
    for fact in (small.url, info.config_hash, "alpha 10", "test-shift", f"{NUM_POINTS} per cloud", "seed 7"):
        assert fact in text
    assert "task frame" in text and "world frame cannot be restored" in text
    assert "45 deg x k" in text and "r x 8/2" in text
    assert f"val {VAL:g}" in text
    markdown = (out / PROVENANCE_MD).read_text().splitlines()
    assert [line[2:] for line in markdown if line.startswith("- ")] == lines


# ---------------------------------------------------------------------------------------------------------
# what the authors' network or loader cannot take: refused with one line
# ---------------------------------------------------------------------------------------------------------


def test_a_path_containing_cloud_is_refused(small: Built, tmp_path: Path) -> None:
    for out in (tmp_path / "pointcloud_export", tmp_path / "cloud" / "air"):
        with pytest.raises(StorageError, match="cloud"):
            export_air(small.url, out, num_points=8)
        assert not out.exists()


def test_bad_arguments_and_missing_datasets_are_storage_errors(small: Built, tmp_path: Path) -> None:
    with pytest.raises(StorageError, match="points"):
        export_air(small.url, tmp_path / "a", num_points=0)
    with pytest.raises(StorageError):
        export_air(str(tmp_path / "no_dataset_here"), tmp_path / "b", num_points=8)
    for kwargs, fragment in (
        ({"num_points": -5}, "--points -5"),
        ({"num_points": 1}, "at least 2"),
        ({"num_points": 8, "seed": -1}, "--seed"),
        ({"num_points": 8, "val_fraction": 1.5}, "--val"),
        ({"num_points": 8, "rotation_names": "degrees"}, "--rotation-names"),
    ):
        with pytest.raises(StorageError, match=fragment):
            export_air(small.url, tmp_path / "c", **kwargs)  # type: ignore[arg-type]
    with pytest.raises(StorageError, match=r"--layout 'scvp': unknown layout; the layouts are 'air' .*'pcnbv'"):
        check_layout("scvp")
    for name in ("air", "mascvp", "nbvnet", "pcnbv"):
        check_layout(name)
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing written, no staging folder


def test_a_non_empty_output_is_refused_and_the_first_export_stays(small: Built, tmp_path: Path) -> None:
    out = tmp_path / "air"
    export_air(small.url, out, num_points=8, seed=1, val_fraction=VAL)
    before = files_under(out)
    with pytest.raises(StorageError, match="not empty; give an empty or new folder"):
        export_air(small.url, out, num_points=16, seed=2, val_fraction=VAL)
    assert files_under(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["air"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(StorageError, match="not a folder"):
        export_air(small.url, tmp_path / "file", num_points=8)
    (tmp_path / "empty").mkdir()
    assert export_air(small.url, tmp_path / "empty", num_points=8).written == len(exportable(small))


def test_an_interrupted_export_leaves_nothing_that_looks_complete(small: Built, tmp_path: Path) -> None:
    def stop(done: int, total: int) -> None:
        if done == total // 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        export_air(small.url, tmp_path / "air", num_points=8, progress=stop)
    assert list(tmp_path.iterdir()) == []  # no OUT, no staging folder
    with pytest.raises(StorageError, match="leaves train_split empty"):  # their trainer would have nothing
        export_air(small.url, tmp_path / "air", num_points=8, val_fraction=1.0)
    assert list(tmp_path.iterdir()) == []


def test_a_dataset_of_other_than_32_views_is_refused(tmp_path: Path) -> None:
    config = GenerationConfig(
        rotations=1, refiner="none", alpha=4, view_space=ViewSpaceConfig(source="generated", count=12)
    )
    url = str(tmp_path / "twelve")
    one_task_dataset(url, "capsule", config)
    with pytest.raises(StorageError, match="has 12 candidate views, but the authors' network has 32 outputs"):
        export_air(url, tmp_path / "air", num_points=8)
    assert not (tmp_path / "air").exists()


def test_rotations_get_the_authors_meaning_or_are_refused(tmp_path: Path) -> None:
    config = GenerationConfig(rotations=3, refiner="none")
    url = str(tmp_path / "thirds")
    built = one_task_dataset(url, "capsule", config, rotation=1)  # a yaw of 120 deg: no rotate_<k> means it
    with pytest.raises(StorageError, match=r"rotation 1 of 3 \(yaw 120 deg\).*--rotation-names yaw"):
        export_air(url, tmp_path / "air", num_points=8, val_fraction=0.0)
    assert not (tmp_path / "air").exists()
    summary = export_air(url, tmp_path / "air", num_points=8, val_fraction=0.0, rotation_names="yaw")
    assert [p.name for p in (tmp_path / "air" / "capsule").iterdir()] == ["yaw_120"]
    assert summary.provenance["rotations"]["folder_of_rotation"] == {"1": "yaw_120"}
    assert any(line.startswith("rotations: folders yaw_<degrees>") for line in summary.lines)
    assert len(cosc_load(tmp_path / "air", "train_split")) == summary.written == len(exportable(built))


# ---------------------------------------------------------------------------------------------------------
# object names the authors' loader cannot take
# ---------------------------------------------------------------------------------------------------------


def test_object_names_containing_cloud_are_refused(tmp_path: Path) -> None:
    """Their loader would rewrite 'cloud' inside the object folder too and miss every companion file."""
    config = GenerationConfig(rotations=1, refiner="none")
    url = str(tmp_path / "named")
    build_dataset(url, ["capsule"], config, rename={"capsule": "cloud_capsule"})
    out = tmp_path / "air"
    with pytest.raises(StorageError, match=r"object 'cloud_capsule'.*rename it"):
        export_air(url, out, num_points=32, val_fraction=0.0)
    assert not out.exists()


def test_two_objects_of_one_name_lose_no_samples(tmp_path: Path) -> None:
    config = GenerationConfig(rotations=1, refiner="none")
    url = str(tmp_path / "two_jobs")
    first = build_dataset(url, ["capsule"], config, rename={"capsule": "thing"}, finalise_index=False)
    second = build_dataset(url, ["l_bracket"], config, rename={"l_bracket": "thing"})
    assert len({s.object_id for s in (*first.samples.values(), *second.samples.values())}) == 2
    out = tmp_path / "air"
    summary = export_air(url, out, num_points=16, val_fraction=0.5)
    count = summary.written
    assert len(list(out.rglob("cloud_*.txt"))) == count == len(exportable(first)) + len(exportable(second))
    train = set((out / "train_split").read_text().split())
    test = set((out / "test_split").read_text().split())
    assert not train & test
    folders = sorted(p.name for p in out.iterdir() if p.is_dir())
    assert len(folders) == 2 and all(name.startswith("thing") for name in folders), folders


# ---------------------------------------------------------------------------------------------------------
# datagen shards export
# ---------------------------------------------------------------------------------------------------------


@pytest.fixture
def cli(monkeypatch: pytest.MonkeyPatch) -> tuple[CliRunner, typer.Typer]:
    monkeypatch.setattr(common.console, "_width", 400)
    monkeypatch.setattr(common.error_console, "_width", 400)
    app = typer.Typer(pretty_exceptions_enable=False, add_completion=False)
    app.add_typer(shards_app, name="shards")  # as datagen/cli/main.py registers it
    return CliRunner(), app


def assert_one_error_line(result, fragment: str) -> None:  # type: ignore[no-untyped-def]
    assert result.exit_code == 2, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert "Traceback" not in result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and fragment in lines[0], result.stderr


def test_cli_export_writes_the_layout_and_says_where(
    cli: tuple[CliRunner, typer.Typer], small: Built, exported: tuple[Path, Export], tmp_path: Path
) -> None:
    runner, app = cli
    out = tmp_path / "via_cli"
    args = ["shards", "export", small.url, str(out), "--layout", "air", "--points", str(NUM_POINTS)]
    result = runner.invoke(app, [*args, "--seed", "7", "--val", str(VAL)])
    assert result.exit_code == 0, result.output
    assert f"exported {len(exportable(small))} samples" in result.stdout
    assert str(out.resolve()) in result.stdout
    assert files_under(out) == files_under(exported[0])  # the same call as export_air(...)
    lines = result.stdout.splitlines()
    assert lines[1:] == list(exported[1].lines[1:])  # every provenance line, printed
    for topic in ("skipped", "dataset:", "points:", "frame:", "rotations:", "views:", "split:", "provenance:"):
        assert any(line.startswith(topic) for line in lines), topic


def test_cli_export_errors_are_one_line(cli: tuple[CliRunner, typer.Typer], small: Built, tmp_path: Path) -> None:
    runner, app = cli
    result = runner.invoke(
        app, ["shards", "export", small.url, str(tmp_path / "my_cloud"), "--layout", "air", "--points", "8"]
    )
    assert_one_error_line(result, "cloud")
    result = runner.invoke(
        app, ["shards", "export", str(tmp_path / "nothing"), str(tmp_path / "x"), "--layout", "air", "--points", "8"]
    )
    assert_one_error_line(result, "dataset.json")
    for extra, fragment in (
        (["--layout", "scvp", "--points", "8"], "unknown layout"),
        (["--layout", "air", "--points", "0"], "--points 0"),
        (["--layout", "air", "--points", "-3"], "--points -3"),
        (["--layout", "air", "--points", "8", "--val", "2"], "--val"),
    ):
        result = runner.invoke(app, ["shards", "export", small.url, str(tmp_path / "y"), *extra])
        assert_one_error_line(result, fragment)
    # a missing required option stays typer's usage error (exit 2), no traceback
    result = runner.invoke(app, ["shards", "export", small.url, str(tmp_path / "y"), "--points", "8"])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert not (tmp_path / "y").exists()
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "cloud_40.txt").write_text("0 0 0\n")
    result = runner.invoke(
        app, ["shards", "export", small.url, str(tmp_path / "full"), "--layout", "air", "--points", "8"]
    )
    assert_one_error_line(result, "is not empty; give an empty or new folder")
    assert [p.name for p in (tmp_path / "full").iterdir()] == ["cloud_40.txt"]
