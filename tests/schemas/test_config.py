"""GenerationConfig: defaults, TOML round trip, hashing and one-line errors (schemas/config.py,
datagen/config_io.py)."""

from __future__ import annotations

import hashlib
import shutil
import tomllib
from importlib import resources
from pathlib import Path

import pytest

from datagen.config_io import config_from_dict, config_to_toml, load_config
from datagen.errors import ConfigError
from datagen.settings import RunSettings
from schemas.config import CameraConfig, GenerationConfig, ViewSpaceConfig, canonical_json

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def builtin_view_space_text() -> str:
    return resources.files("datagen").joinpath("data", "view_space_32.txt").read_text()


# ---------------------------------------------------------------------------------------------------------
# Defaults (docs/pipeline.md sections 0-7)
# ---------------------------------------------------------------------------------------------------------


def test_defaults_are_the_pipeline_values() -> None:
    config = GenerationConfig()
    assert config.seed == 0
    assert config.voxel_size == 0.002
    assert config.grid_offset == (0.2718, 0.3141, 0.1618)
    assert config.size_range == (0.05, 0.15)
    assert config.mm_threshold == 10.0
    assert config.rotations == 8
    assert config.view_space == ViewSpaceConfig(source="builtin", count=32, radius=0.4)
    assert config.num_views == 32
    assert config.imaging == "targets"
    assert config.band == 0.01
    assert config.alpha == 10
    assert config.empty_labels == "keep"


def test_default_camera_is_the_authors_realsense() -> None:
    camera = GenerationConfig().camera
    assert (camera.width, camera.height) == (1280, 720)
    assert camera.fx == pytest.approx(915.6067, abs=5e-5)
    assert camera.fy == pytest.approx(913.3267, abs=5e-5)
    assert camera.cx == pytest.approx(647.1453, abs=5e-5)
    assert camera.cy == pytest.approx(372.5153, abs=5e-5)
    assert camera.max_range == 1.0
    assert camera == CameraConfig()


def test_band_in_key_space_is_25_for_the_defaults() -> None:
    assert GenerationConfig().band_keys_sq == 25
    assert config_from_dict({"band": 0.006, "voxel_size": 0.002}).band_keys_sq == 9
    # (0.009 / 0.003)^2 = 8.999999999999998 in floats: a band of exactly 3 voxels is still |dk|^2 <= 9
    assert config_from_dict({"band": 0.009, "voxel_size": 0.003}).band_keys_sq == 9
    assert config_from_dict({"band": 0.0059, "voxel_size": 0.002}).band_keys_sq == 8


def test_config_is_frozen() -> None:
    config = GenerationConfig()
    with pytest.raises(ValueError):
        config.alpha = 3  # type: ignore[misc]


def test_load_config_none_gives_defaults() -> None:
    assert load_config(None) == GenerationConfig()


def test_run_settings_are_not_part_of_the_config() -> None:
    assert "out" not in GenerationConfig.model_fields
    settings = RunSettings(out="s3://bucket/x", num_workers=3)
    assert settings.refiner_gpus == 0.0
    with pytest.raises(ValueError):
        RunSettings(refiner_gpus=1.5)
    with pytest.raises(ValueError):
        RunSettings(num_workers=0)


# ---------------------------------------------------------------------------------------------------------
# The example configs
# ---------------------------------------------------------------------------------------------------------


def test_example_default_toml_equals_the_defaults() -> None:
    path = EXAMPLES / "default.toml"
    assert load_config(path) == GenerationConfig()
    assert load_config(path).config_hash() == GenerationConfig().config_hash()


def test_example_default_toml_names_every_field() -> None:
    data = tomllib.loads((EXAMPLES / "default.toml").read_text())
    assert set(data) == set(GenerationConfig.model_fields)
    assert set(data["view_space"]) == set(ViewSpaceConfig.model_fields)
    assert set(data["camera"]) == set(CameraConfig.model_fields)


def test_example_default_toml_comments_every_field() -> None:
    lines = (EXAMPLES / "default.toml").read_text().splitlines()
    for index, line in enumerate(lines):
        if "=" in line and not line.lstrip().startswith("#"):
            assert lines[index - 1].lstrip().startswith("#"), f"no comment above {line!r}"


def test_example_pixels_toml_differs_in_imaging_only() -> None:
    config = load_config(EXAMPLES / "pixels.toml")
    assert config.imaging == "pixels"
    assert config.model_copy(update={"imaging": "targets"}) == GenerationConfig()
    assert config.config_hash() != GenerationConfig().config_hash()


# ---------------------------------------------------------------------------------------------------------
# TOML round trip and hashing
# ---------------------------------------------------------------------------------------------------------

VARIANT = {
    "seed": 7,
    "voxel_size": 0.0025,
    "grid_offset": [0.1, 0.2, 0.3],
    "size_range": [0.06, 0.12],
    "rotations": 4,
    "imaging": "pixels",
    "alpha": 5,
    "band": 0.0125,
    "empty_labels": "drop",
    "view_space": {"source": "generated", "count": 20, "radius": 0.5, "generator_seed": 3},
    "camera": {"width": 640, "height": 480, "fx": 500.0, "fy": 501.5, "cx": 320.25, "cy": 240.75},
}


@pytest.mark.parametrize("data", [{}, VARIANT], ids=["defaults", "variant"])
def test_toml_round_trip_keeps_equality_and_hash(tmp_path: Path, data: dict) -> None:
    config = config_from_dict(data)
    path = write(tmp_path / "c.toml", config_to_toml(config))
    loaded = load_config(path)
    assert loaded == config
    assert loaded.config_hash() == config.config_hash()


def test_round_trip_keeps_float_bits(tmp_path: Path) -> None:
    config = config_from_dict({"voxel_size": 0.1 + 0.2, "camera": {"fx": 915.6066894531250}})
    loaded = load_config(write(tmp_path / "c.toml", config_to_toml(config)))
    assert loaded.voxel_size == 0.1 + 0.2  # 0.30000000000000004, not 0.3
    assert loaded.config_hash() == config.config_hash()


@pytest.mark.parametrize(
    ("field", "other"),
    [
        ("label_tie_break", "coverage"),
        ("label_cover_cap", 64),
        ("poco_version", 2),
        ("label_objective", "max_coverage"),
    ],
)
def test_fields_added_later_keep_older_hashes_at_their_default(field: str, other: object) -> None:
    """A dataset made before ``label_tie_break`` (its labels are the 'index' rule's),
    ``label_cover_cap`` (version 1: no covers listed), ``poco_version`` (cKDTree) or the label objectives
    (the paper's cover) existed keeps its hash. Such a dataset was refined with poco_version 1 (a new
    config's default is now the newest judged version)."""
    config = GenerationConfig(poco_version=1)
    data = config.model_dump(mode="json")
    data["poco_weights"] = config.canonical_dict()["poco_weights"]
    later = ("label_tie_break", "label_cover_cap", "poco_version", "label_objective", "label_budget", "label_tau")
    before_the_fields = {k: v for k, v in data.items() if k not in later}
    assert field not in config.canonical_dict()
    assert config.config_hash() == hashlib.sha256(canonical_json(before_the_fields).encode()).hexdigest()
    assert config_from_dict({field: other}).canonical_dict()[field] == other


@pytest.mark.parametrize(
    ("objective", "used", "unused"),
    [
        ("cover", None, ("label_budget", 5)),
        ("max_coverage", ("label_budget", 5), ("label_tau", 0.8)),
        ("partial_cover", ("label_tau", 0.8), ("label_budget", 5)),
    ],
)
def test_only_the_objectives_own_parameter_enters_the_hash(
    objective: str, used: tuple[str, object] | None, unused: tuple[str, object]
) -> None:
    """A label parameter the objective does not read changes no sample, so it never changes the hash; the
    one it reads does."""
    base = config_from_dict({"label_objective": objective})
    assert config_from_dict({"label_objective": objective, unused[0]: unused[1]}).config_hash() == base.config_hash()
    assert unused[0] not in base.canonical_dict()
    if used is not None:
        changed = config_from_dict({"label_objective": objective, used[0]: used[1]})
        assert changed.config_hash() != base.config_hash() and changed.canonical_dict()[used[0]] == used[1]


def test_the_coverage_tie_break_is_only_for_the_cover_objective() -> None:
    with pytest.raises(ConfigError, match="breaks ties by view index"):
        config_from_dict({"label_objective": "max_coverage", "label_tie_break": "coverage"})


def test_tau_keys_reads_tau_as_written() -> None:
    """0.9 of 1,000 keys is 900 (not 901 from the binary 0.9000000000000000222); 0.9 of 1,001 is 901."""
    assert config_from_dict({"label_tau": 0.9}).tau_keys(1000) == 900
    assert config_from_dict({"label_tau": 0.9}).tau_keys(1001) == 901
    assert config_from_dict({"label_tau": 1.0}).tau_keys(7) == 7


def test_hash_is_sha256_hex() -> None:
    digest = GenerationConfig().config_hash()
    assert len(digest) == 64
    int(digest, 16)


CHANGES = [
    {"seed": 1},
    {"voxel_size": 0.003},
    {"grid_offset": [0.2718, 0.3141, 0.1619]},
    {"size_range": [0.05, 0.16]},
    {"mm_threshold": 100.0},
    {"rotations": 9},
    {"gt_density": 128.0},
    {"imaging": "pixels"},
    {"band": 0.012},
    {"refiner": "carve"},
    {"poco_preset": "tiny_sv"},
    {"poco_threshold": 0.6},
    {"finetune_steps": 10},
    {"poco_version": 1},
    {"poco_version": 3},
    {"poisson_depth": 9},
    {"alpha": 11},
    {"empty_labels": "drop"},
    {"solver_time_limit": 20.0},
    {"label_tie_break": "coverage"},
    {"label_cover_cap": 64},
    {"label_objective": "max_coverage"},
    {"label_objective": "max_coverage", "label_budget": 2},
    {"label_objective": "partial_cover", "label_tau": 0.8},
    {"view_space": {"radius": 0.41}},
    {"view_space": {"source": "generated"}},
    {"view_space": {"source": "generated", "generator_seed": 1}},
    {"camera": {"width": 1281}},
    {"camera": {"height": 721}},
    {"camera": {"fx": 915.0}},
    {"camera": {"fy": 913.0}},
    {"camera": {"cx": 640.0}},
    {"camera": {"cy": 360.0}},
    {"camera": {"max_range": 1.5}},
]


def test_every_field_is_covered_by_the_change_list() -> None:
    top = {key for change in CHANGES for key in change}
    # sampling has one allowed value so far; poco_weights files are covered by their own test
    assert top | {"sampling", "poco_weights"} == set(GenerationConfig.model_fields)
    nested = {
        (key, sub) for change in CHANGES for key, value in change.items() if isinstance(value, dict) for sub in value
    }
    assert {sub for key, sub in nested if key == "camera"} == set(CameraConfig.model_fields)
    # count alone cannot change with the built-in source: it is tested below with a generated source
    view_space_keys = {sub for key, sub in nested if key == "view_space"}
    assert view_space_keys | {"count"} == set(ViewSpaceConfig.model_fields)


@pytest.mark.parametrize("change", CHANGES, ids=lambda change: str(change))
def test_hash_changes_with_every_field(change: dict) -> None:
    base = GenerationConfig()
    changed = config_from_dict(change)
    assert changed != base
    assert changed.config_hash() != base.config_hash()


def test_hash_changes_with_view_count() -> None:
    a = config_from_dict({"view_space": {"source": "generated", "count": 32}})
    b = config_from_dict({"view_space": {"source": "generated", "count": 31}})
    assert a.config_hash() != b.config_hash()


def test_hash_ignores_key_order_and_formatting(tmp_path: Path) -> None:
    first = write(
        tmp_path / "a.toml",
        'seed = 3\nimaging = "pixels"\nalpha = 4\n[camera]\nfx = 900.0\nwidth = 1000\n[view_space]\nradius = 0.45\n',
    )
    second = write(
        tmp_path / "b.toml",
        "# same values, other order\n[view_space]\nradius = 0.450\n\n[camera]\nwidth = 1000\nfx = 9.0e2\n",
    )
    second.write_text('alpha = 4\nimaging = "pixels"\nseed = 3\n' + second.read_text())
    a, b = load_config(first), load_config(second)
    assert a == b
    assert a.config_hash() == b.config_hash()
    assert a.config_hash() != GenerationConfig().config_hash()


def test_spelled_out_defaults_hash_like_the_defaults(tmp_path: Path) -> None:
    path = write(tmp_path / "c.toml", "alpha = 10\nrotations = 8\n[camera]\nwidth = 1280\n")
    assert load_config(path).config_hash() == GenerationConfig().config_hash()


# ---------------------------------------------------------------------------------------------------------
# A view-space file enters the hash by its content
# ---------------------------------------------------------------------------------------------------------


def test_view_space_file_hashes_by_content_not_path(tmp_path: Path) -> None:
    text = builtin_view_space_text()
    (tmp_path / "one").mkdir()
    (tmp_path / "two" / "deeper").mkdir(parents=True)
    write(tmp_path / "one" / "views.txt", text)
    write(tmp_path / "two" / "deeper" / "other-name.txt", text)
    config_a = write(tmp_path / "one" / "a.toml", '[view_space]\nsource = "views.txt"\n')
    config_b = write(tmp_path / "two" / "b.toml", '[view_space]\nsource = "deeper/other-name.txt"\n')
    a, b = load_config(config_a), load_config(config_b)
    assert a.view_space.source != b.view_space.source  # two different resolved paths...
    assert Path(a.view_space.source).is_absolute()
    assert a.config_hash() == b.config_hash()  # ...one hash
    # a file is not the built-in view space, even with the same positions
    assert a.config_hash() != GenerationConfig().config_hash()
    assert a.canonical_dict()["view_space"]["source"].startswith("sha256:")


def test_view_space_file_edit_changes_the_hash(tmp_path: Path) -> None:
    views = write(tmp_path / "views.txt", builtin_view_space_text())
    config_path = write(tmp_path / "c.toml", '[view_space]\nsource = "views.txt"\n')
    before = load_config(config_path).config_hash()
    lines = views.read_text().splitlines()
    x, y, z = (float(v) for v in lines[1].split())
    lines[1] = f"{x} {y} {z + 0.001}"
    views.write_text("\n".join(lines) + "\n")
    after = load_config(config_path).config_hash()
    assert before != after
    # and back again
    write(views, builtin_view_space_text())
    assert load_config(config_path).config_hash() == before


def test_view_space_file_config_round_trips(tmp_path: Path) -> None:
    write(tmp_path / "views.txt", builtin_view_space_text())
    config = load_config(write(tmp_path / "c.toml", '[view_space]\nsource = "views.txt"\n'))
    moved = tmp_path / "elsewhere"
    moved.mkdir()
    again = load_config(write(moved / "d.toml", config_to_toml(config)))
    assert again == config
    assert again.config_hash() == config.config_hash()
    # moving the view-space file (and pointing at it) keeps the hash
    shutil.copy(tmp_path / "views.txt", moved / "views.txt")
    relocated = load_config(write(moved / "e.toml", '[view_space]\nsource = "views.txt"\n'))
    assert relocated.config_hash() == config.config_hash()


def test_missing_view_space_file_is_a_config_error(tmp_path: Path) -> None:
    path = write(tmp_path / "c.toml", '[view_space]\nsource = "nowhere.txt"\n')
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert "\n" not in message
    assert "view_space.source" in message
    assert "nowhere.txt" in message
    assert "'builtin'" in message and "'generated'" in message


# ---------------------------------------------------------------------------------------------------------
# Invalid values: one-line ConfigError naming the field and the allowed range
# ---------------------------------------------------------------------------------------------------------


def config_error(data: dict) -> str:
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, origin="my.toml")
    message = str(info.value)
    assert "\n" not in message, message
    assert message.startswith("my.toml: ")
    return message


@pytest.mark.parametrize("value", [0, -0.002, 0.0])
def test_voxel_size_must_be_positive(value: float) -> None:
    message = config_error({"voxel_size": value})
    assert "voxel_size" in message
    assert "allowed range: > 0" in message


def test_alpha_zero_rejected() -> None:
    message = config_error({"alpha": 0})
    assert "alpha" in message
    assert "allowed range: >= 1" in message


def test_alpha_above_view_count_rejected() -> None:
    message = config_error({"alpha": 33})
    assert "alpha = 33" in message
    assert "1..32" in message
    assert "view_space.count" in message
    # alpha = n is allowed
    assert config_from_dict({"alpha": 32}).alpha == 32


def test_alpha_bound_follows_the_view_count() -> None:
    generated = {"source": "generated", "count": 12}
    assert config_from_dict({"alpha": 12, "view_space": generated}).alpha == 12
    message = config_error({"alpha": 13, "view_space": generated})
    assert "alpha = 13" in message and "1..12" in message
    # the default alpha (10) with fewer views is an error too, naming alpha
    message = config_error({"view_space": {"source": "generated", "count": 8}})
    assert "alpha = 10" in message and "1..8" in message


def test_rotations_zero_rejected() -> None:
    message = config_error({"rotations": 0})
    assert "rotations" in message
    assert "allowed range: >= 1" in message


def test_view_count_above_64_rejected() -> None:
    for source in ("builtin", "generated"):
        message = config_error({"view_space": {"source": source, "count": 65}})
        assert "view_space.count = 65" in message
        assert "<= 64" in message
    assert config_from_dict({"view_space": {"source": "generated", "count": 64}}).num_views == 64


def test_builtin_view_space_must_have_32() -> None:
    message = config_error({"view_space": {"count": 20}})
    assert "view_space.count = 20" in message
    assert "generated" in message


def test_unknown_top_level_key_lists_allowed_keys() -> None:
    message = config_error({"alhpa": 3})
    assert "unknown key 'alhpa'" in message
    for key in GenerationConfig.model_fields:
        assert key in message


def test_unknown_nested_key_lists_allowed_keys() -> None:
    message = config_error({"camera": {"focal": 900.0}})
    assert "unknown key 'camera.focal'" in message
    allowed = message.split("allowed keys here:")[1]
    assert [key.strip() for key in allowed.split(",")] == sorted(CameraConfig.model_fields)
    message = config_error({"view_space": {"n": 32}})
    assert "unknown key 'view_space.n'" in message
    assert "count" in message and "radius" in message


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"grid_offset": [1.0, 0.0, 0.0]}, "grid_offset"),
        ({"grid_offset": [0.1, 0.2]}, "grid_offset"),
        ({"size_range": [0.2, 0.1]}, "size_range"),
        ({"size_range": [0.0, 0.1]}, "size_range"),
        ({"imaging": "rays"}, "imaging"),
        ({"empty_labels": "maybe"}, "empty_labels"),
        ({"band": -0.01}, "band"),
        ({"seed": -1}, "seed"),
        ({"voxel_size": float("nan")}, "voxel_size"),
        ({"camera": {"cx": 2000.0}}, "cx"),
        ({"camera": {"width": 8}}, "camera.width"),
        ({"view_space": {"radius": 0}}, "view_space.radius"),
    ],
)
def test_other_invalid_values_name_the_field(data: dict, field: str) -> None:
    assert field in config_error(data)


def test_invalid_value_in_a_file_names_the_file(tmp_path: Path) -> None:
    path = write(tmp_path / "bad.toml", "voxel_size = 0\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert message.startswith(str(path))
    assert "voxel_size" in message and "> 0" in message
    assert "\n" not in message


def test_malformed_toml_rejected(tmp_path: Path) -> None:
    path = write(tmp_path / "broken.toml", "alpha = \nseed = [1,\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert str(path) in message
    assert "not valid TOML" in message
    assert "line 1" in message
    assert "\n" not in message


def test_missing_config_file_rejected(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(tmp_path / "nope.toml")
    message = str(info.value)
    assert "nope.toml" in message
    assert "not found" in message
    assert "\n" not in message


# ---------------------------------------------------------------------------------------------------------
# The built-in POCO weights enter the hash by their content
# ---------------------------------------------------------------------------------------------------------


def changed_copy(source: Path, target: Path) -> Path:
    """The file with its last byte flipped: what an upgrade of the shipped weights looks like."""
    data = bytearray(source.read_bytes())
    data[-1] ^= 0x01
    target.write_bytes(bytes(data))
    return target


def test_builtin_weights_enter_the_hash_by_content(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from schemas import config as config_module

    shipped = config_module.builtin_poco_weights()
    assert shipped.is_file() and shipped.name == "poco_small.pt"
    before = GenerationConfig().config_hash()
    assert GenerationConfig().canonical_dict()["poco_weights"] == "sha256:" + config_module.file_sha256(shipped)
    # the same file by path hashes like "builtin" (content, never path)
    assert GenerationConfig(poco_weights=str(shipped)).config_hash() == before
    # an identical copy keeps the hash; one changed byte changes it
    same = tmp_path / "same.pt"
    same.write_bytes(shipped.read_bytes())
    monkeypatch.setattr(config_module, "BUILTIN_POCO_WEIGHTS_FILE", same)
    assert GenerationConfig().config_hash() == before
    monkeypatch.setattr(config_module, "BUILTIN_POCO_WEIGHTS_FILE", changed_copy(shipped, tmp_path / "new.pt"))
    upgraded = GenerationConfig()
    assert upgraded.config_hash() != before
    # ...while the config, its TOML and the refiner's file stay "builtin"
    assert upgraded.poco_weights == "builtin" and upgraded == GenerationConfig()
    assert tomllib.loads(config_to_toml(upgraded))["poco_weights"] == "builtin"
    from datagen.pipeline.refine.factory import poco_weights_path

    assert poco_weights_path(upgraded) == tmp_path / "new.pt"


def test_missing_builtin_weights_are_one_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from schemas import config as config_module
    from schemas.errors import DatagenError

    monkeypatch.setattr(config_module, "BUILTIN_POCO_WEIGHTS_FILE", tmp_path / "gone.pt")
    with pytest.raises(DatagenError) as info:
        GenerationConfig().config_hash()
    assert "\n" not in str(info.value) and "gone.pt" in str(info.value) and "reinstall datagen" in str(info.value)


def test_refiners_that_never_load_the_builtin_weights_keep_their_hash(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An upgrade of the shipped weights must not change the identity of a `none`/`carve`/`poisson`
    dataset (they never load the weights), so such datasets made before it still resume."""
    from schemas import config as config_module

    others = [GenerationConfig(refiner=name) for name in ("none", "carve", "poisson")]
    before = [c.config_hash() for c in others]
    assert all(c.canonical_dict()["poco_weights"] == "builtin" for c in others)
    shipped = config_module.builtin_poco_weights()
    monkeypatch.setattr(config_module, "BUILTIN_POCO_WEIGHTS_FILE", changed_copy(shipped, tmp_path / "new.pt"))
    assert [c.config_hash() for c in others] == before
    monkeypatch.setattr(config_module, "BUILTIN_POCO_WEIGHTS_FILE", tmp_path / "gone.pt")
    assert [c.config_hash() for c in others] == before  # not even read


def test_a_new_config_takes_the_newest_judged_poco_version_and_a_stored_one_keeps_its_own() -> None:
    """A fresh config refines with `LATEST_POCO_VERSION`; a dataset.json or a ledgered job written before
    the field existed reads as version 1 (what made it), and one that records it keeps it."""
    from schemas.config import LATEST_POCO_VERSION
    from schemas.dataset import DatasetInfo
    from schemas.jobs import JobSpec

    assert GenerationConfig().poco_version == LATEST_POCO_VERSION == 2
    old = GenerationConfig(poco_version=1).model_dump(mode="json")
    del old["poco_version"]
    record = {"schema_version": 3, "config": old, "config_hash": "x", "view_positions": [], "versions": {}}
    assert DatasetInfo.model_validate({**record, "created": "t"}).config.poco_version == 1
    kept = {**old, "poco_version": 2}
    assert DatasetInfo.model_validate({**record, "config": kept, "created": "t"}).config.poco_version == 2
    job = JobSpec.model_validate({"job_id": "j", "objects_file": "f", "out": "o", "config": old, "tasks": []})
    assert job.config.poco_version == 1


def test_poco_version_changes_only_a_poco_datasets_identity() -> None:
    """Only the poco refiner reads the field: other refiners' datasets keep their hash whatever it says."""
    for refiner in ("none", "carve", "poisson"):
        assert config_from_dict({"refiner": refiner, "poco_version": 1}).config_hash() == (
            config_from_dict({"refiner": refiner, "poco_version": 2}).config_hash()
        )
    assert GenerationConfig(poco_version=1).config_hash() != GenerationConfig(poco_version=2).config_hash()
    assert GenerationConfig(poco_version=3).config_hash() != GenerationConfig(poco_version=2).config_hash()


def test_poco_versions_past_the_judged_one_are_chosen_by_name_and_none_past_the_newest_exists() -> None:
    """Versions 3 (ordered neighbour tables) and 4 (the fast network) are there to be asked for; a new
    config still takes the newest judged one, and a version that does not exist is refused by the
    config in the field's own words."""
    from pydantic import ValidationError

    from schemas.config import LATEST_POCO_VERSION, NEWEST_POCO_VERSION, POCO_VERSIONS

    assert sorted(POCO_VERSIONS) == list(range(1, NEWEST_POCO_VERSION + 1))
    assert NEWEST_POCO_VERSION == 4 > LATEST_POCO_VERSION == GenerationConfig().poco_version
    assert GenerationConfig(poco_version=3).poco_version == 3
    for wrong in (NEWEST_POCO_VERSION + 1, 0, "4"):
        with pytest.raises(ValidationError, match="poco_version"):
            GenerationConfig(poco_version=wrong)


def test_a_poco_version_brings_its_preset_threshold_and_weights_unless_the_config_names_them() -> None:
    """`POCO_VERSIONS`: version 4 is the fast_sv network at its own threshold and shipped file; naming
    version 2 alone goes back to version 2's whole network; a named preset or threshold is kept; and the
    earlier versions' configs hash as they did (the recorded hashes below)."""
    from schemas.config import POCO_VERSIONS, builtin_poco_weights, file_sha256

    fourth = GenerationConfig(poco_version=4)
    assert (fourth.poco_preset, fourth.poco_threshold) == ("fast_sv", 0.375)
    assert fourth.poco_weights == "builtin" and fourth.poco_weights_path() == builtin_poco_weights(4)
    assert builtin_poco_weights(4).name == "poco_fast.pt" != builtin_poco_weights(2).name == "poco_small.pt"
    for version in (1, 2, 3):
        config = GenerationConfig(poco_version=version)
        assert (
            (config.poco_preset, config.poco_threshold)
            == ("small_sv", 0.65)
            == (
                POCO_VERSIONS[version].preset,
                POCO_VERSIONS[version].threshold,
            )
        )
    assert GenerationConfig(poco_version=4, poco_threshold=0.5).poco_threshold == 0.5
    assert GenerationConfig(poco_version=4, poco_preset="small_sv").poco_preset == "small_sv"
    assert GenerationConfig(poco_version=2, poco_preset="fast_sv").poco_threshold == 0.65
    data = fourth.canonical_dict()
    assert (data["poco_version"], data["poco_preset"], data["poco_threshold"]) == (4, "fast_sv", 0.375)
    assert data["poco_weights"] == "sha256:" + file_sha256(builtin_poco_weights(4))
    assert fourth.config_hash() not in {GenerationConfig(poco_version=v).config_hash() for v in (1, 2, 3)}


@pytest.mark.parametrize(
    ("fields", "recorded"),
    [
        ({"refiner": "none"}, "2351d4b92c8fe757e16ac7dbeaa5b5d866e15612c2b39e2403f3e1edc7e6dbf0"),
        ({"refiner": "none", "poco_version": 3}, "2351d4b92c8fe757e16ac7dbeaa5b5d866e15612c2b39e2403f3e1edc7e6dbf0"),
        ({"refiner": "carve"}, "48451f7ba8733c686d7b1af429f567ba53c41db91e4dbc975accb0b3c4b632ec"),
        ({"refiner": "poisson"}, "582817a348360073b75c7c8022f9f4bc4e7320c9748bb492abf542fc5fa53414"),
        ({"refiner": "poco"}, "a4a5d2b1c2ae5ebdb47e585d708a24c181f944b93c8badbcdb5504ec26c288a6"),
        ({"refiner": "poco", "poco_version": 1}, "7a7fd1010539c62684e31002577c3545aa56cd2529021138367db8bfb5babc1c"),
    ],
)
def test_each_refiners_configs_keep_the_hash_their_datasets_were_made_with(fields: dict, recorded: str) -> None:
    """Recorded before refiners became registered kinds (`schemas.refiners`): the kind's fields and
    files decide what enters the hash, as the name branches did (the none one is real-train-none's)."""
    assert GenerationConfig(**fields).config_hash() == recorded


def test_an_unknown_refiner_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match="unknown refiner 'marching'; choose one of none, carve, poisson, poco"):
        GenerationConfig(refiner="marching")
