"""Objects files: parsing, resolution, per-line errors, duplicates and object ids
(datagen/pipeline/objects/objects_file.py, datagen/pipeline/objects/spec.py)."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest

from datagen.errors import ObjectsFileError
from datagen.pipeline.objects.objects_file import ObjectLineError, object_line, read_objects_file, variants_listing
from datagen.pipeline.objects.spec import ObjectOptions, ObjectSpec, builtin_object_id, file_object_id
from datagen.shapes import builtins

TETRA = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
OTHER_TETRA = TETRA.replace("v 0 0 0.1", "v 0 0 0.12")

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture
def meshes(tmp_path: Path) -> Path:
    """A folder with two small meshes and a sub-folder with a third."""
    (tmp_path / "tetra.obj").write_text(TETRA)
    (tmp_path / "other.obj").write_text(OTHER_TETRA)
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "deep.obj").write_text(OTHER_TETRA + "# a comment changes the bytes\n")
    return tmp_path


def listing_of(folder: Path, text: str, name: str = "objects.txt"):
    path = folder / name
    path.write_text(text)
    return read_objects_file(path)


def only_error(folder: Path, line: str) -> ObjectLineError:
    listing = listing_of(folder, f"# header\n\n{line}\n")
    assert listing.objects == []
    (error,) = listing.errors
    return error


def smallest_builtin() -> str:
    assert "capsule" in builtins.builtin_names()
    return "capsule"


# ---------------------------------------------------------------------------------------------------------
# Good lines
# ---------------------------------------------------------------------------------------------------------


def test_comments_and_blank_lines_are_skipped(meshes: Path) -> None:
    listing = listing_of(
        meshes,
        "# a comment\n\n   \n\t\ntetra.obj   # trailing comment\n  # indented comment\nother.obj\n\n",
    )
    assert listing.errors == []
    assert [spec.name for spec in listing.objects] == ["tetra", "other"]
    assert [spec.line for spec in listing.objects] == [5, 7]
    assert len(listing.entries) == 2


def test_relative_paths_resolve_against_the_objects_file(meshes: Path, tmp_path: Path, monkeypatch) -> None:
    lists = meshes / "lists"
    lists.mkdir()
    (lists / "objects.txt").write_text("../tetra.obj\n../sub/deep.obj\n")
    elsewhere = tmp_path / "cwd"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # the working directory must not matter
    listing = read_objects_file(lists / "objects.txt")
    assert listing.errors == []
    sources = [spec.source for spec in listing.objects]
    assert sources == [str((meshes / "tetra.obj").resolve()), str((meshes / "sub" / "deep.obj").resolve())]
    assert all(Path(source).is_absolute() for source in sources)


def test_relative_objects_file_path_from_another_folder(meshes: Path, monkeypatch) -> None:
    (meshes / "sub" / "objects.txt").write_text("deep.obj\n../tetra.obj\n")
    monkeypatch.chdir(meshes)
    listing = read_objects_file(Path("sub") / "objects.txt")
    assert [Path(spec.source) for spec in listing.objects] == [
        (meshes / "sub" / "deep.obj").resolve(),
        (meshes / "tetra.obj").resolve(),
    ]


def test_absolute_paths_and_quoted_paths_with_spaces(meshes: Path) -> None:
    spaced = meshes / "with space.obj"
    spaced.write_text(TETRA + "\n")
    listing = listing_of(meshes, f'{(meshes / "tetra.obj").resolve()}\n"with space.obj" name=spaced\n')
    assert listing.errors == []
    assert [spec.source for spec in listing.objects] == [
        str((meshes / "tetra.obj").resolve()),
        str(spaced.resolve()),
    ]


def test_options_are_parsed(meshes: Path) -> None:
    listing = listing_of(
        meshes,
        "tetra.obj units=mm up=y size=0.12 name=first\n"
        "other.obj size=1e-1 units=m\n"
        "sub/deep.obj name=third units=auto up=z\n",
    )
    assert listing.errors == []
    first, second, third = listing.objects
    assert first.name == "first"
    assert first.options == ObjectOptions(units="mm", up="y", size=0.12)
    assert second.name == "other"  # default name: the file stem
    assert second.options == ObjectOptions(units="m", up="z", size=0.1)
    assert third.name == "third"
    assert third.options == ObjectOptions()
    assert first.origin == f"{meshes / 'objects.txt'}:1"
    assert first.task_id(3) == f"{first.object_id[:16]}-r3"
    assert first.id_prefix == int(first.object_id[:16], 16)
    assert not first.is_builtin


def test_builtin_is_resolved_with_its_generator_identity(meshes: Path) -> None:
    name = smallest_builtin()
    listing = listing_of(meshes, f"builtin:{name}\nbuiltin:{name} size=0.1 name=small_{name}\n")
    assert listing.errors == []
    plain, sized = listing.objects
    identity = builtins.builtin_generator_identity(name)
    assert plain.is_builtin and plain.source == f"builtin:{name}"
    assert plain.name == name
    assert plain.generator == identity
    assert plain.object_id == builtin_object_id(identity, ObjectOptions())
    assert sized.object_id == builtin_object_id(identity, ObjectOptions(size=0.1))
    assert sized.object_id != plain.object_id
    assert sized.name == f"small_{name}"


def test_variant_option_is_parsed_and_names_the_variant(meshes: Path) -> None:
    name = smallest_builtin()
    listing = listing_of(
        meshes,
        f"tetra.obj variant=7\ntetra.obj variant=0 size=0.1\nbuiltin:{name} variant=3\n"
        "other.obj variant=12 name=mine\n",
    )
    assert listing.errors == []
    seven, zero, builtin, named = listing.objects
    assert seven.options == ObjectOptions(variant=7)
    assert zero.options == ObjectOptions(size=0.1, variant=0)
    assert builtin.options == ObjectOptions(variant=3)
    assert [seven.name, zero.name, builtin.name, named.name] == ["tetra-v7", "tetra-v0", f"{name}-v3", "mine"]
    assert builtin.object_id == builtin_object_id(builtins.builtin_generator_identity(name), ObjectOptions(variant=3))


def test_category_labels_an_object_without_changing_its_id(meshes: Path) -> None:
    listing = listing_of(
        meshes,
        "tetra.obj category=02691156\n'other.obj' name=o category='two words'\nbuiltin:capsule category=c\n",
    )
    assert listing.errors == []
    tetra, other, capsule = listing.objects
    assert (tetra.category, other.category, capsule.category) == ("02691156", "two words", "c")
    plain = listing_of(meshes, "tetra.obj\n", name="plain.txt").objects[0]
    assert plain.category is None and plain.object_id == tetra.object_id
    lines = [object_line(spec, meshes) for spec in listing.objects]
    assert lines == [
        "tetra.obj category=02691156",
        "other.obj name=o 'category=two words'",
        "builtin:capsule category=c",
    ]
    varied = variants_listing(listing, 1, 0, meshes / "varied.txt").splitlines()
    assert all("category=" in line for line in varied[1:])


def test_builtin_ids_differ_between_builtins(meshes: Path) -> None:
    names = builtins.builtin_names()
    listing = listing_of(meshes, "".join(f"builtin:{name}\n" for name in names))
    assert listing.errors == []
    assert len({spec.object_id for spec in listing.objects}) == len(names)


def test_unknown_builtin_names_the_builtins(meshes: Path) -> None:
    error = only_error(meshes, "builtin:teacup")
    assert error.line == 3
    assert "unknown built-in 'teacup'" in error.message
    for name in builtins.builtin_names():
        assert name in error.message
    assert "datagen objects builtins" in error.message


def test_the_example_objects_file_resolves_to_the_shared_meshes() -> None:
    examples = EXAMPLES.resolve()
    shared = (examples / ".." / ".." / "shared" / "meshes").resolve()
    if not shared.is_dir():
        pytest.skip(f"shared meshes not found at {shared}")
    assert shared == (examples.parent.parent / "shared" / "meshes").resolve()
    listing = read_objects_file(EXAMPLES / "shared-meshes.txt")
    assert listing.errors == []
    assert len(listing.objects) >= 3
    for spec in listing.objects:
        assert Path(spec.source).parent == shared


# ---------------------------------------------------------------------------------------------------------
# Bad lines: an ObjectLineError with the file, the line and the fix; the other lines go on
# ---------------------------------------------------------------------------------------------------------


def assert_line_error(error: ObjectLineError, folder: Path, line: int, *needles: str) -> None:
    text = str(error)
    assert "\n" not in text
    assert text.startswith(f"{folder / 'objects.txt'}:{line}: ")
    assert error.origin == str(folder / "objects.txt")
    assert error.line == line
    for needle in needles:
        assert needle in error.message, (needle, error.message)


@pytest.mark.parametrize("option", ["size", "=3", "name="])
def test_malformed_option(meshes: Path, option: str) -> None:
    error = only_error(meshes, f"tetra.obj {option}")
    assert_line_error(error, meshes, 3, f"malformed option {option!r}", "key=value", "units", "size")


def test_unknown_key(meshes: Path) -> None:
    error = only_error(meshes, "tetra.obj scale=2")
    assert_line_error(error, meshes, 3, "unknown key 'scale'", "allowed keys: name, units, up, size")


@pytest.mark.parametrize(
    ("option", "needles"),
    [
        ("units=cm", ("units='cm'", "units=auto", "units=m", "units=mm")),
        ("units=MM", ("units='MM'", "units=mm")),
        ("up=x", ("up='x'", "up=z", "up=y")),
        ("up=-z", ("up='-z'", "up=z or up=y")),
    ],
)
def test_bad_units_or_up(meshes: Path, option: str, needles: tuple[str, ...]) -> None:
    assert_line_error(only_error(meshes, f"tetra.obj {option}"), meshes, 3, *needles)


@pytest.mark.parametrize("value", ["abc", "-1", "0", "nan", "inf", "0.1m"])
def test_bad_size(meshes: Path, value: str) -> None:
    error = only_error(meshes, f"tetra.obj size={value}")
    assert_line_error(error, meshes, 3, "size=", value, "metres", "size=0.12")


@pytest.mark.parametrize("value", ["-1", "abc", "1.5", "+3", "0x10", "1e3", "\u0663", "seven"])
def test_bad_variant(meshes: Path, value: str) -> None:
    error = only_error(meshes, f"tetra.obj variant={value}")
    assert_line_error(error, meshes, 3, f"variant={value!r}", "non-negative integer seed", "variant=3")


def test_missing_mesh_file(meshes: Path) -> None:
    error = only_error(meshes, "sub/nope.obj")
    assert_line_error(
        error, meshes, 3, "mesh file not found", str((meshes / "sub" / "nope.obj").resolve()), "fix the path"
    )


def test_folder_instead_of_a_mesh(meshes: Path) -> None:
    error = only_error(meshes, "sub")
    assert_line_error(error, meshes, 3, "is a folder", "mesh file")


def test_key_given_twice(meshes: Path) -> None:
    error = only_error(meshes, "tetra.obj size=0.1 size=0.2")
    assert_line_error(error, meshes, 3, "'size' given twice", "keep one")


def test_options_before_the_path(meshes: Path) -> None:
    error = only_error(meshes, "size=0.1 tetra.obj")
    assert_line_error(error, meshes, 3, "must start with a mesh path")


def test_unbalanced_quote(meshes: Path) -> None:
    error = only_error(meshes, '"tetra.obj name=x')
    assert_line_error(error, meshes, 3, "quote")


def test_quoted_path_with_a_hash(meshes: Path) -> None:
    (meshes / "part#2.obj").write_text(TETRA)
    listing = listing_of(meshes, '"part#2.obj"  # the second part\n')
    assert listing.errors == []
    assert listing.objects[0].source == str((meshes / "part#2.obj").resolve())


def test_byte_order_mark_is_ignored(meshes: Path) -> None:
    (meshes / "objects.txt").write_bytes(b"\xef\xbb\xbftetra.obj\n")
    listing = read_objects_file(meshes / "objects.txt")
    assert listing.errors == []


def test_a_bad_line_does_not_stop_the_others(meshes: Path) -> None:
    listing = listing_of(meshes, "tetra.obj\ntetra.obj units=km name=t2\nother.obj\nmissing.obj\n")
    assert [entry.line for entry in listing.entries] == [1, 2, 3, 4]
    assert [spec.name for spec in listing.objects] == ["tetra", "other"]
    assert [error.line for error in listing.errors] == [2, 4]
    assert isinstance(listing.entries[1], ObjectLineError)
    assert isinstance(listing.entries[2], ObjectSpec)


# ---------------------------------------------------------------------------------------------------------
# Duplicates
# ---------------------------------------------------------------------------------------------------------


def test_same_object_twice_names_both_lines(meshes: Path) -> None:
    listing = listing_of(meshes, "# objects\ntetra.obj size=0.1\n\nother.obj\ntetra.obj size=0.1 name=again\n")
    assert [spec.line for spec in listing.objects] == [2, 4]
    (error,) = listing.errors
    assert_line_error(error, meshes, 5, "same object as line 2", "2 and 5")


def test_same_object_with_equivalent_spelling_is_a_duplicate(meshes: Path) -> None:
    # ./tetra.obj, size 0.10 and an explicit units=auto are the same mesh with the same options
    listing = listing_of(meshes, "tetra.obj size=0.1\n./tetra.obj size=0.10 units=auto up=z name=t2\n")
    (error,) = listing.errors
    assert_line_error(error, meshes, 2, "same object as line 1")


def test_same_bytes_under_another_path_is_the_same_object(meshes: Path) -> None:
    (meshes / "sub" / "copy.obj").write_bytes((meshes / "tetra.obj").read_bytes())
    listing = listing_of(meshes, "tetra.obj\nsub/copy.obj\n")
    (error,) = listing.errors
    assert_line_error(error, meshes, 2, "same object as line 1")


def test_same_builtin_twice_is_a_duplicate(meshes: Path) -> None:
    name = smallest_builtin()
    listing = listing_of(meshes, f"builtin:{name}\nbuiltin:{name} name=second\n")
    (error,) = listing.errors
    assert_line_error(error, meshes, 2, "same object as line 1")


def test_same_file_with_different_options_is_not_a_duplicate(meshes: Path) -> None:
    listing = listing_of(
        meshes,
        "tetra.obj name=a\ntetra.obj size=0.1 name=b\ntetra.obj up=y name=c\ntetra.obj units=mm name=d\n",
    )
    assert listing.errors == []
    assert len({spec.object_id for spec in listing.objects}) == 4


@pytest.mark.parametrize("layout", ["same-file-other-options", "same-stem-other-folders"])
def test_default_names_do_not_make_distinct_objects_errors(meshes: Path, layout: str) -> None:
    if layout == "same-file-other-options":
        text = "tetra.obj\ntetra.obj size=0.1\n"
    else:
        (meshes / "a").mkdir()
        (meshes / "b").mkdir()
        (meshes / "a" / "model.obj").write_text(TETRA)
        (meshes / "b" / "model.obj").write_text(OTHER_TETRA)
        text = "a/model.obj\nb/model.obj\n"
    listing = listing_of(meshes, text)
    assert listing.errors == []
    assert len(listing.objects) == 2


def test_explicit_name_used_twice_is_an_error(meshes: Path) -> None:
    listing = listing_of(meshes, "tetra.obj name=thing\nother.obj name=thing\n")
    (error,) = listing.errors
    assert_line_error(error, meshes, 2, "name 'thing'", "line 1", "name=")


# ---------------------------------------------------------------------------------------------------------
# Files that are unusable as a whole
# ---------------------------------------------------------------------------------------------------------


def test_objects_file_with_only_comments(meshes: Path) -> None:
    path = meshes / "objects.txt"
    path.write_text("# nothing yet\n\n   # still nothing\n")
    with pytest.raises(ObjectsFileError) as info:
        read_objects_file(path)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message
    assert "lists no objects" in message
    assert "builtin:NAME" in message


def test_empty_objects_file(meshes: Path) -> None:
    path = meshes / "objects.txt"
    path.write_text("")
    with pytest.raises(ObjectsFileError, match="lists no objects"):
        read_objects_file(path)


def test_missing_objects_file(tmp_path: Path) -> None:
    with pytest.raises(ObjectsFileError) as info:
        read_objects_file(tmp_path / "absent.txt")
    message = str(info.value)
    assert "absent.txt" in message and "not found" in message
    assert "\n" not in message


def test_binary_objects_file(tmp_path: Path) -> None:
    path = tmp_path / "objects.txt"
    path.write_bytes(b"\xff\xfe\x00\x81" * 50)
    with pytest.raises(ObjectsFileError, match="not a text file"):
        read_objects_file(path)


def test_objects_file_is_a_folder(tmp_path: Path) -> None:
    with pytest.raises(ObjectsFileError) as info:
        read_objects_file(tmp_path)
    assert str(tmp_path) in str(info.value)


# ---------------------------------------------------------------------------------------------------------
# Object ids
# ---------------------------------------------------------------------------------------------------------


def id_of(folder: Path, line: str) -> str:
    (spec,) = listing_of(folder, line + "\n", name=f"ids-{os.urandom(4).hex()}.txt").objects
    return spec.object_id


def test_object_id_is_sha256_of_bytes_and_canonical_options(meshes: Path) -> None:
    data = (meshes / "tetra.obj").read_bytes()
    options = ObjectOptions(units="mm", up="y", size=0.12)
    expected = hashlib.sha256(data + b"\0" + options.canonical().encode()).hexdigest()
    assert file_object_id(data, options) == expected
    assert id_of(meshes, "tetra.obj units=mm up=y size=0.12") == expected


def test_object_id_is_stable(meshes: Path, tmp_path: Path) -> None:
    first = id_of(meshes, "tetra.obj size=0.1")
    assert id_of(meshes, "tetra.obj size=0.1") == first
    assert id_of(meshes, "tetra.obj size=0.1 name=renamed") == first  # the name is not part of the id
    assert id_of(meshes, "tetra.obj   size=0.100   # comment") == first
    moved = tmp_path / "moved"
    moved.mkdir()
    (moved / "renamed.obj").write_bytes((meshes / "tetra.obj").read_bytes())
    assert id_of(moved, "renamed.obj size=0.1") == first  # by content, not by path


def test_object_id_changes_with_the_file_bytes(meshes: Path) -> None:
    before = id_of(meshes, "tetra.obj")
    (meshes / "tetra.obj").write_text(TETRA + "\n")  # one more byte
    assert id_of(meshes, "tetra.obj") != before
    (meshes / "tetra.obj").write_text(TETRA)
    assert id_of(meshes, "tetra.obj") == before


@pytest.mark.parametrize("option", ["units=m", "units=mm", "up=y", "size=0.1", "size=0.11"])
def test_object_id_changes_with_options(meshes: Path, option: str) -> None:
    assert id_of(meshes, f"tetra.obj {option}") != id_of(meshes, "tetra.obj")


def test_no_variant_keeps_todays_canonical_json_and_object_id(meshes: Path) -> None:
    """Datasets made before ``variant=`` existed keep their object ids (and so task ids and seeds)."""
    options = ObjectOptions(units="mm", up="y", size=0.12)
    assert options.canonical() == '{"size":0.12,"units":"mm","up":"y"}'
    assert ObjectOptions().canonical() == '{"size":null,"units":"auto","up":"z"}'
    known = "4e31735845da8c2dc157fd9609c837f1e9dc4e2624e7314bc7a21e76b02ab0e4"  # made before variant= existed
    assert file_object_id(TETRA.encode(), options) == known
    assert id_of(meshes, "tetra.obj units=mm up=y size=0.12") == known


def test_object_id_differs_per_variant_and_is_stable(meshes: Path) -> None:
    ids = [id_of(meshes, "tetra.obj"), *(id_of(meshes, f"tetra.obj variant={seed}") for seed in (0, 1, 2, 99))]
    assert len(set(ids)) == len(ids)
    assert id_of(meshes, "tetra.obj variant=1") == ids[2]
    assert id_of(meshes, "tetra.obj variant=01 name=x") == ids[2]  # the seed's value, not its spelling
    assert ObjectOptions(variant=1).canonical() == '{"size":null,"units":"auto","up":"z","variant":1}'


def test_same_variant_twice_is_a_duplicate_other_variants_are_not(meshes: Path) -> None:
    listing = listing_of(meshes, "tetra.obj\ntetra.obj variant=1\ntetra.obj variant=2\ntetra.obj variant=1\n")
    (error,) = listing.errors
    assert_line_error(error, meshes, 4, "same object as line 2")
    assert [spec.name for spec in listing.objects] == ["tetra", "tetra-v1", "tetra-v2"]


def test_builtin_id_ignores_mesh_bytes_but_not_the_generator() -> None:
    name = smallest_builtin()
    identity = builtins.builtin_generator_identity(name)
    base = builtin_object_id(identity, ObjectOptions())
    assert builtin_object_id(dict(identity), ObjectOptions()) == base
    bumped = {**identity, "version": identity["version"] + 1}
    assert builtin_object_id(bumped, ObjectOptions()) != base
    tweaked = {**identity, "params": {**identity["params"], "radius": identity["params"]["radius"] + 0.001}}
    assert builtin_object_id(tweaked, ObjectOptions()) != base
