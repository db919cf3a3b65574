"""The next-view export layouts (mascvp, nbvnet, pcnbv; docs/authors-code.md sections 7.3-7.5): every file
holds exactly what the reader serves, the arrays have the shapes and dtypes the authors' trainers load,
and every refusal is one line that leaves nothing behind. The air layout has its own tests
(test_export.py)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import typer
from support import storage as fx
from typer.testing import CliRunner

from datagen.cli.shards import shards_app
from datagen.pipeline.keys import pack_keys
from schemas.shard import GT_KEYS
from storage import StorageError, finalise, init_dataset, open_dataset, open_location, write_task
from storage.export import LAYOUTS, PROVENANCE_JSON, PROVENANCE_MD, Export, cpp_text, export
from storage.readers import Dataset
from storage.samples import mask_bits

NEXT_VIEW_LAYOUTS = ("mascvp", "nbvnet", "pcnbv")
GT_POINTS = 64
VAL = 0.5


@pytest.fixture(scope="module")
def url(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = str(tmp_path_factory.mktemp("layouts") / "ds")
    fx.build_dataset(path, finalise_index=True)
    return path


@pytest.fixture(scope="module")
def exports(url: str, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Export]:
    root = tmp_path_factory.mktemp("exports")
    extra = {"pcnbv": {"gt_points": GT_POINTS}}
    return {
        name: export(name, url, root / name, seed=3, val_fraction=VAL, **extra.get(name, {}))  # type: ignore[arg-type]
        for name in NEXT_VIEW_LAYOUTS
    }


def array_rows(out: Path) -> list[dict[str, str]]:
    with (out / "array_rows.csv").open() as handle:
        return list(csv.DictReader(handle))


def row_of(ds: Dataset) -> dict[str, int]:
    return {sid: i for i, sid in enumerate(ds.index.column("sample_id").to_pylist())}


def files_under(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def grid_text_matches(path: Path, grid: np.ndarray) -> None:
    """32,768 lines, each a value as C++ prints a double (6 significant digits), within that rounding of
    the reader's float32 grid, in x-major order."""
    lines = path.read_text().splitlines()
    assert len(lines) == 32768
    values = np.array([float(line) for line in lines])
    assert all(f"{value:g}" == line for value, line in zip(values.tolist(), lines, strict=True))
    np.testing.assert_allclose(values, grid.reshape(-1).astype(np.float64), rtol=0, atol=5e-7)


# ---------------------------------------------------------------------------------------------------------
# what the files hold
# ---------------------------------------------------------------------------------------------------------


def test_every_layout_writes_its_case_files_and_arrays_for_the_written_samples(
    url: str, exports: dict[str, Export]
) -> None:
    ds = open_dataset(url)
    case_files = {"mascvp": ("grid", "state", "ids"), "nbvnet": ("grid", "id"), "pcnbv": ("cloud", "state", "score")}
    for name, summary in exports.items():
        rows = array_rows(summary.out)
        assert len(rows) == summary.written == len(ds) - len(summary.skipped)
        assert [r["split"] for r in rows] == sorted((r["split"] for r in rows), key=("train", "test").index)
        for side in ("train", "test"):
            assert [int(r["row"]) for r in rows if r["split"] == side] == list(
                range(sum(r["split"] == side for r in rows))
            )
        expected = {f"{r['folder']}/{kind}_{r['case']}.txt" for r in rows for kind in case_files[name]}
        written = {str(p.relative_to(summary.out)) for p in summary.out.glob("*/*/*.txt")}
        assert written == expected, name
        shard_rows = ds.index.column("row").to_pylist()
        for r in rows:  # <c> is the sample's row in its task's shard
            assert int(r["case"]) == shard_rows[row_of(ds)[r["sample_id"]]]
        assert not [p for p in summary.out.parent.iterdir() if p.name.startswith(".")]  # no staging left


def test_mascvp_files_and_arrays_hold_the_stored_grid_state_and_label(url: str, exports: dict[str, Export]) -> None:
    ds = open_dataset(url)
    out = exports["mascvp"].out
    rows = array_rows(out)
    arrays = {
        side: {k: np.load(out / side / f"{k}.npy") for k in ("grid", "vss", "label")} for side in ("train", "test")
    }
    for side, found in arrays.items():
        count = sum(r["split"] == side for r in rows)
        assert found["grid"].shape == (count, 32768) and found["grid"].dtype == np.float32
        assert found["vss"].shape == found["label"].shape == (count, 32)
        assert found["vss"].dtype == found["label"].dtype == np.float32
    for r in rows:
        i = row_of(ds)[r["sample_id"]]
        view_state, label = ds.masks(i)
        grid = ds.next_view(i, grid=True).grid
        assert grid is not None
        folder, c, position = out / r["folder"], r["case"], int(r["row"])
        grid_text_matches(folder / f"grid_{c}.txt", grid)
        assert (folder / f"state_{c}.txt").read_text().split() == [str(int(b)) for b in mask_bits(view_state, 32)]
        assert [int(v) for v in (folder / f"ids_{c}.txt").read_text().split()] == np.flatnonzero(
            mask_bits(label, 32)
        ).tolist()
        found = arrays[r["split"]]
        np.testing.assert_array_equal(found["grid"][position], grid.reshape(-1))  # x-major, exactly the reader's
        np.testing.assert_array_equal(found["vss"][position], mask_bits(view_state, 32))
        np.testing.assert_array_equal(found["label"][position], mask_bits(label, 32))
        assert label  # empty labels are skipped


def test_mascvp_arrays_load_as_their_scvp_dataset_loads_them(exports: dict[str, Export]) -> None:
    """ma_scvp train.py: vss and label paths are GRID_PATH with 'grid' replaced; SCVPDataset loads all
    three with allow_pickle, reshapes a grid to (1, 32, 32, 32) and makes float32 tensors."""
    grid_path = str(exports["mascvp"].out / "train" / "grid.npy")
    grid = np.load(grid_path, allow_pickle=True)
    vss = np.load(grid_path.replace("grid", "vss"), allow_pickle=True)
    label = np.load(grid_path.replace("grid", "label"), allow_pickle=True)
    assert len(grid) == len(vss) == len(label) > 0
    assert np.reshape(grid[0], (1, 32, 32, 32)).shape == (1, 32, 32, 32)
    assert label.sum(axis=1).min() >= 1  # their recall divides by it


def test_nbvnet_files_and_arrays_hold_the_stored_grid_and_best_view(url: str, exports: dict[str, Export]) -> None:
    ds = open_dataset(url)
    out = exports["nbvnet"].out
    rows = array_rows(out)
    best_column = ds.index.column("best_view").to_pylist()
    for side in ("train", "test"):
        grids, labels = np.load(out / side / "grids.npy"), np.load(out / side / "labels.npy")
        count = sum(r["split"] == side for r in rows)
        assert grids.shape == (count, 32768) and grids.dtype == np.float32
        assert labels.shape == (count,) and labels.dtype == np.int64
        for r in (r for r in rows if r["split"] == side):
            i, position = row_of(ds)[r["sample_id"]], int(r["row"])
            next_view = ds.next_view(i, grid=True)
            assert next_view.grid is not None
            assert (out / r["folder"] / f"id_{r['case']}.txt").read_text() == f"{next_view.best_view}\n"
            assert labels[position] == next_view.best_view == best_column[i] >= 0
            np.testing.assert_array_equal(grids[position], next_view.grid.reshape(-1))
            if position < 3:
                grid_text_matches(out / r["folder"] / f"grid_{r['case']}.txt", next_view.grid)
    positions = np.loadtxt(out / "points_in_sphere.txt")
    np.testing.assert_allclose(positions, np.asarray(ds.info.view_positions), atol=5e-7)


def test_pcnbv_files_and_tensors_hold_the_observed_cloud_state_and_score(url: str, exports: dict[str, Export]) -> None:
    torch = pytest.importorskip("torch")
    ds = open_dataset(url)
    config = ds.info.config
    out = exports["pcnbv"].out
    rows = array_rows(out)
    tensors = {
        side: [torch.load(out / "dataset" / f"{stem}_{side}.pt") for stem in PCNBV_STEMS] for side in ("train", "test")
    }
    for side, (clouds, gts, states, targets) in tensors.items():
        count = sum(r["split"] == side for r in rows)
        assert tuple(clouds.shape) == (count, 512, 3) and tuple(gts.shape) == (count, GT_POINTS, 3)
        assert tuple(states.shape) == tuple(targets.shape) == (count, 32)
        assert {t.dtype for t in (clouds, gts, states, targets)} == {torch.float32}
    for r in rows:
        i, position, c = row_of(ds)[r["sample_id"]], int(r["row"]), r["case"]
        clouds, gts, states, targets = (t[position].numpy() for t in tensors[r["split"]])
        view_state, _ = ds.masks(i)
        next_view = ds.next_view(i)
        score = next_view.view_gains / next_view.visible_size
        folder = out / r["folder"]
        lines = (folder / f"score_{c}.txt").read_text().splitlines()
        assert lines == [f"{value:g}" for value in score.tolist()]
        np.testing.assert_array_equal(targets, score.astype(np.float32))
        assert (folder / f"state_{c}.txt").read_text().split() == [str(int(b)) for b in mask_bits(view_state, 32)]
        np.testing.assert_array_equal(states, mask_bits(view_state, 32))
        observed = pack_keys(ds.keys(i, "observed").astype(np.int64))
        assert np.isin(point_keys(clouds, config), observed).all()  # drawn from what the case saw
        if observed.size >= 512:
            assert np.unique(point_keys(clouds, config)).size == 512  # without replacement
        text = np.loadtxt(folder / f"cloud_{c}.txt")
        assert text.shape == (512, 3)
        np.testing.assert_allclose(text, clouds, rtol=5e-6, atol=1e-9)  # the tensor's points, 6 digits
        gt = pack_keys(ds.shard(ds.index.column("shard")[i].as_py()).array(GT_KEYS).astype(np.int64))
        assert np.isin(point_keys(gts, config), gt).all()


PCNBV_STEMS = ("accumulate_pointclouds", "gt_point_clouds", "view_statess", "target_values")


def point_keys(points: np.ndarray, config) -> np.ndarray:  # type: ignore[no-untyped-def]
    scaled = points.astype(np.float64) / config.voxel_size + np.asarray(config.grid_offset)
    keys = np.floor(scaled).astype(np.int64)
    assert np.abs(scaled - keys - 0.5).max() < 1e-3  # a voxel centre
    return pack_keys(keys)


def test_skips_follow_each_layouts_trainer(url: str, exports: dict[str, Export]) -> None:
    ds = open_dataset(url)
    empty = {
        sid
        for sid, label in zip(*(ds.index.column(c).to_pylist() for c in ("sample_id", "label")), strict=True)
        if not label
    }
    assert empty  # the capsule has cases that need no view
    assert exports["mascvp"].skipped == dict.fromkeys(sorted(empty), "empty label")
    assert exports["nbvnet"].skipped == {} == exports["pcnbv"].skipped  # gains exist for every case
    for name, summary in exports.items():
        provenance = json.loads((summary.out / PROVENANCE_JSON).read_text())
        assert provenance == summary.provenance and provenance["layout"] == name
        assert provenance["written"] == summary.written
        assert provenance["arrays"]  # shapes and dtypes of every array file
        lines = (summary.out / PROVENANCE_MD).read_text()
        assert f"--layout {name}" in lines and "case numbers:" in lines and "split:" in lines


def test_exports_are_deterministic_in_their_seed(url: str, exports: dict[str, Export], tmp_path: Path) -> None:
    first = files_under(exports["pcnbv"].out)
    export("pcnbv", url, tmp_path / "again", seed=3, val_fraction=VAL, gt_points=GT_POINTS)
    export("pcnbv", url, tmp_path / "other", seed=4, val_fraction=VAL, gt_points=GT_POINTS)
    assert files_under(tmp_path / "again") == first  # tensors and provenance included
    other = files_under(tmp_path / "other")
    clouds = [k for k in first if "cloud_" in k]
    assert clouds and all(k in other for k in clouds) and any(other[k] != first[k] for k in clouds)
    assert all(other[k] == first[k] for k in first if "score_" in k or "state_" in k)


# ---------------------------------------------------------------------------------------------------------
# refusals: one line, nothing left behind
# ---------------------------------------------------------------------------------------------------------


def refused(fragment: str, *args: object, **kwargs: object) -> str:
    with pytest.raises(StorageError, match=fragment) as caught:
        export(*args, **kwargs)  # type: ignore[arg-type]
    message = str(caught.value)
    assert "\n" not in message
    return message


def test_a_dataset_older_than_version_3_is_refused_with_relabel_as_the_fix(tmp_path: Path) -> None:
    old = str(tmp_path / "v2")
    fx.build_dataset(old, schema_version=2, finalise_index=True)
    for name in NEXT_VIEW_LAYOUTS:
        message = refused("version-2 dataset keeps no next-view labels", name, old, tmp_path / name)
        assert f"datagen shards relabel {old} --out NEW_URL" in message
    assert export("air", old, tmp_path / "air", num_points=8, val_fraction=VAL).written  # air needs no gains
    assert sorted(p.name for p in tmp_path.iterdir()) == ["air", "v2"]


def test_a_dataset_of_other_than_32_views_is_refused(tmp_path: Path) -> None:
    """Refused from dataset.json alone, before a shard is read: its view list says 12 here (the shards are
    the 32-view fixture's, which nothing reads)."""
    twelve = str(tmp_path / "twelve")
    info = fx.dataset_info()
    location = open_location(twelve)
    init_dataset(location, info.model_copy(update={"view_positions": info.view_positions[:12]}))
    write_task(location, fx.payloads()[0], fx.ATTEMPT)
    finalise(location)
    assert open_dataset(twelve).num_views == 12
    for name in NEXT_VIEW_LAYOUTS:
        refused("has 12 candidate views, but the authors' network has 32 outputs", name, twelve, tmp_path / name)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["twelve"]


def test_output_and_option_refusals(url: str, exports: dict[str, Export], tmp_path: Path) -> None:
    for name in NEXT_VIEW_LAYOUTS:
        refused("is not empty; give an empty or new folder", name, url, exports[name].out)
    refused("replacing 'grid' in the whole path", "mascvp", url, tmp_path / "grids" / "out")
    refused(r"--points 8: layout nbvnet writes no point clouds", "nbvnet", url, tmp_path / "a", num_points=8)
    refused(r"--gt-points 9: layout mascvp writes no ground-truth clouds", "mascvp", url, tmp_path / "a", gt_points=9)
    refused(r"--gt-points 1: give at least 2", "pcnbv", url, tmp_path / "a", gt_points=1)
    refused(r"--layout 'scvp': unknown layout", "scvp", url, tmp_path / "a")
    refused("--layout air: give --points N", "air", url, tmp_path / "a")
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    summary = export("pcnbv", url, tmp_path / "cloud_ok", val_fraction=VAL, gt_points=4)  # no loader replaces 'cloud'
    assert summary.written


@pytest.mark.parametrize("name", NEXT_VIEW_LAYOUTS)
def test_an_interrupted_export_leaves_nothing_that_looks_complete(url: str, name: str, tmp_path: Path) -> None:
    def stop(done: int, total: int) -> None:
        if done == total // 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        export(
            name,
            url,
            tmp_path / "out",
            val_fraction=VAL,
            progress=stop,
            **({"gt_points": 4} if name == "pcnbv" else {}),
        )
    assert list(tmp_path.iterdir()) == []  # no OUT, no staging folder


# ---------------------------------------------------------------------------------------------------------
# datagen shards export --layout ...
# ---------------------------------------------------------------------------------------------------------


@pytest.fixture
def app() -> typer.Typer:
    app = typer.Typer(pretty_exceptions_enable=False, add_completion=False)
    app.add_typer(shards_app, name="shards")
    return app


def test_cli_dispatches_every_layout_and_lists_them(
    runner: CliRunner, app: typer.Typer, url: str, exports: dict[str, Export], tmp_path: Path
) -> None:
    out = tmp_path / "nbvnet"
    result = runner.invoke(
        app, ["shards", "export", url, str(out), "--layout", "nbvnet", "--seed", "3", "--val", "0.5"]
    )
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines()[1:] == list(exports["nbvnet"].lines[1:])
    assert files_under(out) == files_under(exports["nbvnet"].out)
    help_text = " ".join(runner.invoke(app, ["shards", "export", "--help"]).stdout.split())
    for name in LAYOUTS:
        assert f"'{name}'" in help_text
    result = runner.invoke(app, ["shards", "export", url, str(tmp_path / "x"), "--layout", "mascvp", "--points", "8"])
    assert result.exit_code == 2 and "Traceback" not in result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --points 8: layout mascvp writes no point clouds")
    assert not (tmp_path / "x").exists()


def test_cpp_text_prints_as_cpp_ostream_does() -> None:
    """The default ostream format of a double: %g with 6 significant digits (trailing zeros dropped)."""
    assert cpp_text([0.5, 0.7005671, 1e-05, 0.0, 123456789.0]) == "0.5\n0.700567\n1e-05\n0\n1.23457e+08\n"
    assert cpp_text([[1.0, -0.25, 3.0]], columns=3) == "1 -0.25 3\n"
    assert cpp_text([]) == ""
