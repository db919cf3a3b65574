"""The command line (datagen/cli): config show, objects builtins/show/synth and scan, through typer's
CliRunner; user errors are one `error:` line and a non-zero exit code, never a traceback."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest
from typer.testing import CliRunner

from datagen.cli.main import app
from datagen.config_io import load_config
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.shapes import builtins
from schemas.config import LATEST_POCO_VERSION, GenerationConfig

FAST_BUILTIN = "capsule"
"""The quickest built-in to prepare and scan (about 0.1 s for one rotation)."""

TETRA = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def error_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("error:")]


def assert_user_error(result, code: int = 2) -> str:
    """A user error: the given exit code, exactly one `error:` line, no traceback."""
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output
    (line,) = error_lines(result.stderr)
    assert result.stderr.strip() == line
    return line


# ---------------------------------------------------------------------------------------------------------
# config show
# ---------------------------------------------------------------------------------------------------------


def test_config_show_prints_default_toml_and_hash(runner: CliRunner) -> None:
    result = runner.invoke(app, ["config", "show"])
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    assert lines[0] == f"# config hash: {GenerationConfig().config_hash()}"
    data = tomllib.loads(result.stdout)
    assert GenerationConfig.model_validate(data) == GenerationConfig()
    assert data["poco_version"] == LATEST_POCO_VERSION == 2  # a fresh config: the newest judged refiner version


def test_config_show_with_a_config(runner: CliRunner, tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text('imaging = "pixels"\nalpha = 4\n')
    result = runner.invoke(app, ["config", "show", "--config", str(path)])
    assert result.exit_code == 0, result.output
    expected = load_config(path)
    assert f"# config hash: {expected.config_hash()}" in result.stdout.splitlines()
    assert expected.config_hash() != GenerationConfig().config_hash()
    assert GenerationConfig.model_validate(tomllib.loads(result.stdout)) == expected


def test_config_show_output_loads_back_to_the_same_hash(runner: CliRunner, tmp_path: Path) -> None:
    source = tmp_path / "c.toml"
    source.write_text("rotations = 4\n[camera]\nfx = 900.5\n")
    first = runner.invoke(app, ["config", "show", "-c", str(source)])
    again = tmp_path / "again.toml"
    again.write_text(first.stdout)
    second = runner.invoke(app, ["config", "show", "-c", str(again)])
    assert second.exit_code == 0
    assert second.stdout == first.stdout


@pytest.mark.parametrize(
    ("text", "needles"),
    [
        ("voxel_size = 0\n", ("voxel_size", "> 0")),
        ("alpha = 33\n", ("alpha = 33", "1..32")),
        ("rotations = 0\n", ("rotations", ">= 1")),
        ("[view_space]\nsource = 'generated'\ncount = 65\n", ("view_space.count", "<= 64")),
        ("colour = 'red'\n", ("unknown key 'colour'", "voxel_size")),
        ("alpha = = 3\n", ("not valid TOML",)),
    ],
)
def test_config_show_bad_config_is_one_error_line(
    runner: CliRunner, tmp_path: Path, text: str, needles: tuple[str, ...]
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    result = runner.invoke(app, ["config", "show", "--config", str(path)])
    line = assert_user_error(result)
    assert line.startswith(f"error: {path}: ")
    for needle in needles:
        assert needle in line
    assert "config hash" not in result.stdout


def test_config_show_missing_config(runner: CliRunner, tmp_path: Path) -> None:
    result = runner.invoke(app, ["config", "show", "--config", str(tmp_path / "absent.toml")])
    line = assert_user_error(result)
    assert "absent.toml" in line and "not found" in line


# ---------------------------------------------------------------------------------------------------------
# objects builtins / show / synth
# ---------------------------------------------------------------------------------------------------------


def test_objects_builtins_lists_every_builtin(runner: CliRunner) -> None:
    result = runner.invoke(app, ["objects", "builtins"])
    assert result.exit_code == 0, result.output
    names = builtins.builtin_names()
    assert len(names) >= 5
    lines = result.stdout.splitlines()  # off a terminal: the title, then tab-separated whole lines
    assert lines[:2] == ["built-in shapes", "name\tfamily\tdescription"]
    rows = [line.split("\t")[0] for line in lines[2:]]
    assert sorted(rows) == sorted(names) and all(line.count("\t") == 2 for line in lines[1:])
    for name in names:
        assert builtins.get_builtin(name).description in result.stdout


def test_objects_show_good_and_bad_lines(runner: CliRunner, tmp_path: Path) -> None:
    (tmp_path / "tetra.obj").write_text(TETRA)
    (tmp_path / "nan.obj").write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    path = tmp_path / "objects.txt"
    path.write_text(
        "# two good objects, four bad lines\n"
        "tetra.obj\n"
        f"builtin:{FAST_BUILTIN}\n"
        "missing.obj\n"
        "tetra.obj colour=red name=t2\n"
        "nan.obj\n"
        "tetra.obj size=0.9 name=huge\n"
    )
    result = runner.invoke(app, ["objects", "show", str(path)])
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    out = result.stdout
    listing = read_objects_file(path)
    tetra, capsule = listing.objects[:2]
    assert tetra.object_id[:16] in out and capsule.object_id[:16] in out
    assert FAST_BUILTIN in out
    # each error is shown, on its own row
    assert f"mesh file not found: {(tmp_path / 'missing.obj').resolve()}" in out
    assert "unknown key 'colour'" in out
    assert "NaN or infinite vertex coordinates" in out
    assert "does not fit the image" in out
    rows = {line.split("\t")[0]: line for line in out.splitlines() if line.count("\t") == 7}
    assert "not found" in rows["4"] and "colour" in rows["5"] and "NaN" in rows["6"] and "fit" in rows["7"]
    assert "2 objects ready, 4 with errors" in out


def test_objects_show_all_good_exits_zero(runner: CliRunner, tmp_path: Path) -> None:
    (tmp_path / "tetra.obj").write_text(TETRA)
    path = tmp_path / "objects.txt"
    path.write_text("tetra.obj\n")
    result = runner.invoke(app, ["objects", "show", str(path)])
    assert result.exit_code == 0, result.output
    assert "1 objects ready, 0 with errors" in result.stdout


def test_objects_show_error_text_is_not_markup(runner: CliRunner, tmp_path: Path) -> None:
    path = tmp_path / "objects.txt"
    path.write_text("scan[final].obj\nscan[/v2].obj\n")
    result = runner.invoke(app, ["objects", "show", str(path)])
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert result.exit_code == 1
    assert "scan[final].obj" in result.stdout
    assert "scan[/v2].obj" in result.stdout


def test_objects_show_missing_file(runner: CliRunner, tmp_path: Path) -> None:
    result = runner.invoke(app, ["objects", "show", str(tmp_path / "nothing.txt")])
    line = assert_user_error(result)
    assert "nothing.txt" in line and "not found" in line


def test_objects_synth_writes_meshes_and_a_listing(runner: CliRunner, tmp_path: Path) -> None:
    out = tmp_path / "synth"
    result = runner.invoke(app, ["objects", "synth", "--count", "2", "--seed", "3", "--out", str(out)])
    assert result.exit_code == 0, result.output
    listing = read_objects_file(out / "objects.txt")
    assert listing.errors == []
    assert len(listing.objects) == 2
    for spec in listing.objects:
        assert Path(spec.source).parent == out.resolve()
        assert Path(spec.source).stat().st_size > 0
    assert "wrote 2 meshes" in result.stdout
    # same seed, same bytes
    again = tmp_path / "again"
    assert runner.invoke(app, ["objects", "synth", "-n", "2", "-s", "3", "-o", str(again)]).exit_code == 0
    for spec in listing.objects:
        name = Path(spec.source).name
        assert (again / name).read_bytes() == (out / name).read_bytes()


def test_objects_synth_rejects_count_zero(runner: CliRunner, tmp_path: Path) -> None:
    result = runner.invoke(app, ["objects", "synth", "--count", "0", "--out", str(tmp_path / "x")])
    assert result.exit_code == 2
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("case", ["count", "out-is-a-file"])
def test_objects_synth_user_errors_are_one_line(runner: CliRunner, tmp_path: Path, case: str) -> None:
    if case == "count":
        args = ["--count", "100001", "--out", str(tmp_path / "x")]
    else:
        (tmp_path / "file").write_text("")
        args = ["--count", "1", "--out", str(tmp_path / "file")]
    result = runner.invoke(app, ["objects", "synth", *args])
    assert result.exit_code == 2
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)


# ---------------------------------------------------------------------------------------------------------
# scan
# ---------------------------------------------------------------------------------------------------------


def test_scan_one_builtin_rotation(runner: CliRunner, tmp_path: Path) -> None:
    path = tmp_path / "objects.txt"
    path.write_text(f"builtin:{FAST_BUILTIN}\n")
    result = runner.invoke(app, ["scan", "--objects", str(path), "--rotations", "0"])
    assert result.exit_code == 0, result.output
    out = result.stdout
    assert "targets imaging, 32 views" in out
    rows = [line.split("\t") for line in out.splitlines() if line.count("\t") == 7]
    assert rows[0] == ["object", "rot", "P_gt", "union V", "keys/view", "only-1-view", "rays", "s"]
    (row,) = [cells for cells in rows if cells[0] == FAST_BUILTIN]
    values = [cell.strip() for cell in row]
    assert values[1] == "0"  # the rotation
    p_gt, union, per_view, rays = (int(values[i]) for i in (2, 3, 4, 6))
    assert p_gt > 1000
    assert 0 < per_view <= union <= p_gt
    assert rays > 0
    assert "1 task in" in out
    assert error_lines(out) == []


def test_scan_with_a_config_and_bad_lines(runner: CliRunner, tmp_path: Path) -> None:
    config = tmp_path / "c.toml"
    config.write_text('rotations = 4\n[view_space]\nsource = "generated"\ncount = 12\nradius = 0.45\n')
    path = tmp_path / "objects.txt"
    path.write_text(f"builtin:{FAST_BUILTIN}\nbuiltin:nope\n")
    result = runner.invoke(app, ["scan", "--objects", str(path), "--config", str(config), "--rotations", "3"])
    assert result.exit_code == 1, result.output
    assert "12 views" in result.stdout
    assert "1 task in" in result.stdout
    (line,) = error_lines(result.stdout)
    assert f"{path}:2: unknown built-in 'nope'" in line


def test_scan_rotation_out_of_range(runner: CliRunner, tmp_path: Path) -> None:
    path = tmp_path / "objects.txt"
    path.write_text(f"builtin:{FAST_BUILTIN}\n")
    result = runner.invoke(app, ["scan", "--objects", str(path), "--rotations", "8"])
    line = assert_user_error(result)
    assert "--rotations '8'" in line and "0..7" in line


def test_scan_empty_objects_file(runner: CliRunner, tmp_path: Path) -> None:
    path = tmp_path / "objects.txt"
    path.write_text("# nothing here yet\n\n")
    result = runner.invoke(app, ["scan", "--objects", str(path)])
    line = assert_user_error(result, code=2)
    assert line.startswith(f"error: {path}: lists no objects")


def test_scan_missing_objects_file(runner: CliRunner, tmp_path: Path) -> None:
    result = runner.invoke(app, ["scan", "--objects", str(tmp_path / "none.txt")])
    line = assert_user_error(result, code=2)
    assert "none.txt" in line and "not found" in line
