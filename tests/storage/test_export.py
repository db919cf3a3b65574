"""storage.export.export_air and ``datagen shards export``: the authors' text layout (authors-pipeline.md
7.2), checked file by file against the pipeline's own samples, and read back by a mini reader that
follows AIR's COSC_Dataset loading rules."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import pytest
import typer
from support.torch_data import SMALL_OBJECTS, Built, bits, build_dataset, cached_dataset
from typer.testing import CliRunner

from datagen.cli import common
from datagen.cli.shards import shards_app
from datagen.pipeline.keys import pack_keys
from schemas.config import GenerationConfig
from storage import StorageError, open_dataset
from storage.export import export_air

NUM_POINTS = 300
VAL = 0.34


@pytest.fixture(scope="session")
def small(tmp_path_factory: pytest.TempPathFactory) -> Built:
    return cached_dataset("small", tmp_path_factory.mktemp("export_small"))


@pytest.fixture(scope="session")
def exported(small: Built, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    out = tmp_path_factory.mktemp("air_export") / "air"
    return out, export_air(small.url, out, num_points=NUM_POINTS, seed=7, val_fraction=VAL)


def files_under(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def read_ids(path: str | Path) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # an empty label is an empty file
        return np.loadtxt(path, dtype=np.int64, ndmin=1)


def cosc_load(root: Path, split_file: str, num_views: int = 32) -> list[dict[str, object]]:
    """AIR's COSC_Dataset rules (authors-pipeline.md 7.2): objects from a split file, one name per line;
    under ``<root>/<obj>/<rotate dir>/`` every file whose name starts with 'cloud' is a sample; its
    companions are the whole path with 'cloud' replaced by 'state' and by 'ids'; gt = zeros(n);
    gt[ids] = 1."""
    names = [line.strip() for line in (root / split_file).read_text().splitlines() if line.strip()]
    items = []
    for name in names:
        object_dir = os.path.join(str(root), name)
        for rotate in os.listdir(object_dir):
            rotate_dir = os.path.join(object_dir, rotate)
            for file in os.listdir(rotate_dir):
                if not file.startswith("cloud"):
                    continue
                path = os.path.join(rotate_dir, file)
                cloud = np.loadtxt(path, dtype=np.float32)
                state = np.loadtxt(path.replace("cloud", "state"), dtype=np.float32)
                ids = read_ids(path.replace("cloud", "ids"))
                gt = np.zeros(num_views, dtype=np.float32)
                gt[ids] = 1
                items.append({"path": path, "object": name, "cloud": cloud, "state": state, "gt": gt})
    return items


def expected_by_file(url: str, built: Built) -> dict[str, object]:
    """'<obj>/rotate_<r>/cloud_<row>.txt' -> the pipeline's sample, from the dataset index."""
    index = open_dataset(url).index
    out = {}
    for sid, name, rotation, row in zip(
        index.column("sample_id").to_pylist(),
        index.column("object_name").to_pylist(),
        index.column("rotation").to_pylist(),
        index.column("row").to_pylist(),
        strict=True,
    ):
        out[f"{name}/rotate_{rotation}/cloud_{row}.txt"] = built.samples[sid]
    return out


def point_keys(points: np.ndarray, config: GenerationConfig) -> np.ndarray:
    """Packed keys of exported points (voxel centres written with 6 decimals)."""
    scaled = points.astype(np.float64) / config.voxel_size + np.asarray(config.grid_offset)
    keys = np.floor(scaled).astype(np.int64)
    assert np.abs(scaled - keys - 0.5).max() < 1e-3  # at the centre of its voxel
    return pack_keys(keys)


# ---------------------------------------------------------------------------------------------------------
# layout and content
# ---------------------------------------------------------------------------------------------------------


def test_layout_has_one_cloud_state_ids_triple_per_sample(small: Built, exported: tuple[Path, int]) -> None:
    out, count = exported
    expected = expected_by_file(small.url, small)
    assert count == len(small.samples) == len(expected)
    clouds = {str(p.relative_to(out)) for p in out.rglob("cloud_*.txt")}
    assert clouds == set(expected)
    every = {str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()}
    triples = {c.replace("cloud", k) for c in clouds for k in ("cloud", "state", "ids")}
    assert every == triples | {"train_split", "test_split"}


def test_files_hold_exactly_the_samples(small: Built, exported: tuple[Path, int]) -> None:
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


def test_split_files_partition_the_objects(small: Built, exported: tuple[Path, int]) -> None:
    out, _ = exported
    train = (out / "train_split").read_text().splitlines()
    test = (out / "test_split").read_text().splitlines()
    names = {s.object_name for s in small.samples.values()}
    assert set(train) | set(test) == names == set(SMALL_OBJECTS)
    assert not set(train) & set(test)
    assert len(test) == round(VAL * len(names)) == 1
    assert len(train) == len(set(train)) and len(test) == len(set(test))


def test_authors_loader_reads_what_export_wrote(small: Built, exported: tuple[Path, int]) -> None:
    out, count = exported
    expected = expected_by_file(small.url, small)
    items = cosc_load(out, "train_split") + cosc_load(out, "test_split")
    assert len(items) == count
    for item in items:
        relative = str(Path(str(item["path"])).relative_to(out))
        sample = expected[relative]
        cloud = item["cloud"]
        assert isinstance(cloud, np.ndarray) and cloud.shape == (NUM_POINTS, 3) and cloud.dtype == np.float32
        np.testing.assert_array_equal(item["state"], bits(sample.case, 32))
        np.testing.assert_array_equal(item["gt"], bits(sample.label, 32))
        assert item["object"] == sample.object_name


def test_export_is_deterministic_in_its_seed(small: Built, exported: tuple[Path, int], tmp_path: Path) -> None:
    out, _ = exported
    again = tmp_path / "again"
    other = tmp_path / "other"
    export_air(small.url, again, num_points=NUM_POINTS, seed=7, val_fraction=VAL)
    export_air(small.url, other, num_points=NUM_POINTS, seed=8, val_fraction=VAL)
    first = files_under(out)
    assert files_under(again) == first
    changed = files_under(other)
    assert changed.keys() == first.keys()
    assert any(changed[k] != first[k] for k in first if "cloud_" in k)
    assert all(changed[k] == first[k] for k in first if "state_" in k or "ids_" in k)


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


# ---------------------------------------------------------------------------------------------------------
# object names the authors' loader cannot take
# ---------------------------------------------------------------------------------------------------------


def test_object_names_containing_cloud_are_refused_or_loadable(tmp_path: Path) -> None:
    config = GenerationConfig(rotations=1, refiner="none")
    url = str(tmp_path / "named")
    built = build_dataset(url, ["capsule"], config, rename={"capsule": "cloud_capsule"})
    out = tmp_path / "air"
    try:
        count = export_air(url, out, num_points=32, val_fraction=0.0)
    except StorageError:
        return  # refusing, with a message, is fine
    items = cosc_load(out, "train_split")
    assert len(items) == count == len(built.samples)


def test_two_objects_of_one_name_lose_no_samples(tmp_path: Path) -> None:
    config = GenerationConfig(rotations=1, refiner="none")
    url = str(tmp_path / "two_jobs")
    first = build_dataset(url, ["capsule"], config, rename={"capsule": "thing"}, finalise_index=False)
    second = build_dataset(url, ["l_bracket"], config, rename={"l_bracket": "thing"})
    assert len({s.object_id for s in (*first.samples.values(), *second.samples.values())}) == 2
    out = tmp_path / "air"
    try:
        count = export_air(url, out, num_points=16, val_fraction=0.5)
    except StorageError:
        return
    assert len(list(out.rglob("cloud_*.txt"))) == count == len(first.samples) + len(second.samples)
    train = set((out / "train_split").read_text().split())
    test = set((out / "test_split").read_text().split())
    assert not train & test


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


def assert_one_error_line(result, fragment: str) -> None:
    assert result.exit_code == 2, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert "Traceback" not in result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and fragment in lines[0], result.stderr


def test_cli_export_writes_the_layout_and_says_where(
    cli: tuple[CliRunner, typer.Typer], small: Built, exported: tuple[Path, int], tmp_path: Path
) -> None:
    runner, app = cli
    out = tmp_path / "via_cli"
    args = ["shards", "export", small.url, str(out), "--layout", "air", "--points", str(NUM_POINTS)]
    result = runner.invoke(app, [*args, "--seed", "7", "--val", str(VAL)])
    assert result.exit_code == 0, result.output
    assert f"exported {len(small.samples)} samples" in result.stdout
    assert str(out.resolve()) in result.stdout
    assert files_under(out) == files_under(exported[0])  # the same call as export_air(...)


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
    # options typer validates itself: usage errors (exit 2), no traceback
    for extra in (["--layout", "mascvp", "--points", "8"], ["--layout", "air", "--points", "0"], ["--points", "8"]):
        result = runner.invoke(app, ["shards", "export", small.url, str(tmp_path / "y"), *extra])
        assert result.exit_code == 2 and "Traceback" not in result.output
    assert not (tmp_path / "y").exists()
