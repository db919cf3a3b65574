"""``datagen config show``, ``datagen objects builtins | show | synth | variants | scan`` and ``datagen scan``: a
job's inputs (generation configs, objects files, built-in, synthetic and varied shapes) and what each view
sees.

Plain functions; `datagen.cli.main` registers them.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn
from rich.table import Table
from rich.text import Text

from datagen.cli.common import (
    Cell,
    ConfigOption,
    IntervalProgress,
    console,
    error_console,
    plural,
    print_rows,
    print_table,
    say,
    user_errors,
)
from datagen.errors import DatagenError, OutputError

if TYPE_CHECKING:
    from datagen.pipeline.objects.scan import MeshCheck
    from datagen.pipeline.objects.spec import ObjectSpec
    from schemas.config import GenerationConfig


def config_show(config: ConfigOption = None) -> None:
    """Print the resolved generation config as TOML, with its hash."""
    from datagen.config_io import config_to_toml, load_config

    with user_errors():
        resolved = load_config(config)
        console.print(f"# config hash: {resolved.config_hash()}", markup=False, highlight=False)
        console.print(config_to_toml(resolved), markup=False, highlight=False, end="")


def objects_builtins() -> None:
    """List the built-in shapes (use them as builtin:NAME in an objects file)."""
    from datagen.shapes import builtins

    table = Table("name", "family", "description", title="built-in shapes")
    for name in builtins.builtin_names():
        shape = builtins.get_builtin(name)
        table.add_row(name, shape.family, shape.description)
    print_table(table)


def objects_show(
    objects: Annotated[Path, typer.Argument(help="Objects file.")],
    config: ConfigOption = None,
) -> None:
    """Resolve and prepare every line of an objects file; show each object or the line's error."""
    from datagen.config_io import load_config
    from datagen.pipeline.objects.objects_file import ObjectLineError, read_objects_file
    from datagen.pipeline.objects.prepare import prepare_object
    from datagen.pipeline.thread_limits import single_threaded_blas

    with user_errors(), single_threaded_blas():
        resolved = load_config(config)
        listing = read_objects_file(objects)
        rows: list[list[Cell]] = []
        warnings: list[str] = []
        failures = 0
        for entry in listing.entries:
            if isinstance(entry, ObjectLineError):
                failures += 1
                rows.append([str(entry.line), "-", Text(entry.message, style="red"), "", "", "", "", ""])
                continue
            try:
                prepared = prepare_object(entry, resolved)
            except DatagenError as exc:
                failures += 1
                rows.append([str(entry.line), entry.name, Text(str(exc), style="red"), "", "", "", "", ""])
                continue
            warned = prepared.flat_warning()
            if warned:
                warnings.append(warned)
            rows.append(
                [
                    str(entry.line),
                    entry.name,
                    entry.object_id[:16],
                    str(len(prepared.faces)),
                    "yes" if prepared.watertight else Text("no", style="yellow"),
                    prepared.units_guessed,
                    f"{prepared.scale:.4g}",
                    f"{prepared.size:.4f}",
                ]
            )
        print_rows(["line", "name", "object id", "faces", "watertight", "units", "scale", "size m"], rows)
        for warning in warnings:
            error_console.print(Text("warning: ", style="yellow") + Text(warning), highlight=False, soft_wrap=True)
        _print_variants(listing.objects)
        console.print(f"{len(listing.entries) - failures} objects ready, {failures} with errors")
        if failures:
            raise typer.Exit(1)


def _print_variants(specs: list[ObjectSpec]) -> None:
    """One line per variant: the deformation its seed draws (the table has no room for it)."""
    from datagen.pipeline.objects.variants import describe_variant

    for spec in specs:
        parameters = describe_variant(spec)
        if parameters is not None:
            say(f"line {spec.line} {spec.name}: {parameters}")


def objects_synth(
    count: Annotated[int, typer.Option("--count", "-n", min=1, max=100_000, help="How many meshes.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the meshes and objects.txt.")],
    seed: Annotated[int, typer.Option("--seed", "-s", min=0, help="Same seed, same bytes.")] = 0,
) -> None:
    """Write N seeded, varied, watertight meshes and an objects file listing them."""
    from datagen.shapes.synthetic import synthesize

    with user_errors():
        listing = synthesize(count, seed, out)
        console.print(f"wrote {count} meshes and {listing}")


def objects_variants(
    objects: Annotated[Path, typer.Argument(help="Objects file whose objects to vary.")],
    count: Annotated[int, typer.Option("--count", "-n", help="Variants per object (1 to 1000).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Objects file to write; its paths start at its folder.")],
    seed: Annotated[int, typer.Option("--seed", "-s", help="Draws the variant seeds; same seed, same bytes.")] = 0,
) -> None:
    """Write an objects file listing each object of OBJECTS followed by COUNT seeded shape variants of it."""
    from datagen.pipeline.objects.objects_file import read_objects_file, variants_listing

    with user_errors():
        listing = read_objects_file(objects)
        _write_text(out, variants_listing(listing, count, seed, out))
        say(f"wrote {out}: {len(listing.objects)} objects, each followed by {count} variants")


def objects_scan(
    folder: Annotated[Path, typer.Argument(help="Folder of meshes: ShapeNetCore, ModelNet or any tree.")],
    out: Annotated[
        Path | None, typer.Option("--out", "-o", help="Objects file to write (paths relative to it); else stdout.")
    ] = None,
    check: Annotated[
        bool, typer.Option("--check", help="Also load every mesh; leave out and name those that will not load.")
    ] = False,
    config: ConfigOption = None,
) -> None:
    """Write an objects file listing every mesh under FOLDER, named by its path, with its category where
    the layout has one; name each file left out and why (byte-identical copies of a listed file too).
    Reads only each file's header, unless --check."""
    from datagen.config_io import load_config
    from datagen.pipeline.objects.scan import SNIFFERS, scan_listing, scan_meshes
    from datagen.pipeline.thread_limits import single_threaded_blas

    with user_errors(), single_threaded_blas():
        result = scan_meshes(folder, _mesh_check(load_config(config)) if check else None)
        if not result.meshes:
            raise DatagenError(
                f"{result.root}: holds no mesh files ({len(result.skipped)} skipped); "
                f"give a folder of {', '.join(sorted(SNIFFERS))} files"
            )
        report = console
        if out is None:
            console.file.write(scan_listing(result, None))  # as written: no markup, emoji codes or wrapping
            console.file.flush()
            report = error_console
        else:
            _write_text(out, scan_listing(result, Path(out).absolute().parent.resolve()))
        categories = len(result.categories)
        summary = (
            f"{len(result.meshes)} meshes in {categories} categories" if categories else f"{len(result.meshes)} meshes"
        )
        where = f"wrote {out}: " if out is not None else "listed "
        report.print(
            f"{where}{summary}; skipped {len(result.skipped)} files, left out {result.companions} "
            "materials, textures and other companion files",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )
        if result.skipped:
            print_rows(["skipped", "why"], [[str(s.path), Text(s.reason, style="red")] for s in result.skipped], report)
        for warned in result.warnings:
            error_console.print(
                f"warning: {warned.path}: {warned.reason}", markup=False, highlight=False, soft_wrap=True
            )


def objects_split(
    objects: Annotated[list[Path], typer.Argument(help="Objects files whose objects to split (e.g. objects scan's).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for train.txt, val.txt and test.txt.")],
    test: Annotated[float, typer.Option("--test", help="Share of each stratum's meshes for testing.")] = 0.2,
    val: Annotated[float, typer.Option("--val", help="Share of each stratum's meshes for validation.")] = 0.1,
    seed: Annotated[int, typer.Option("--seed", "-s", min=0, help="Same meshes and seed, same split.")] = 0,
    hold: Annotated[
        list[Path] | None,
        typer.Option("--hold", help="Objects file of evaluation-only meshes: kept out of every set (repeatable)."),
    ] = None,
) -> None:
    """Split objects by mesh into training, validation and test objects files that cannot leak: lines of
    the same mesh bytes (variants included) share a set, each stratum (category, else the mesh's folder)
    is split in the same shares, and meshes named by --hold files are in none."""
    from datagen.pipeline.objects.objects_file import read_objects_file
    from datagen.pipeline.objects.split import SPLITS, SplitShares, split_listing, split_objects

    with user_errors():
        listings = [read_objects_file(path) for path in objects]
        held = [read_objects_file(path) for path in hold or []]
        for listing in [*listings, *held]:
            for error in listing.errors:
                error_console.print(f"skipped {error}", markup=False, highlight=False, soft_wrap=True)
        split = split_objects(listings, SplitShares(test=test, val=val), seed, held)
        folder = out.absolute().resolve()
        if folder.exists() and not folder.is_dir():
            raise OutputError(f"{out}: is a file; give --out a folder for train.txt, val.txt and test.txt")
        sources = " ".join(relative_path_text(path, folder) for path in objects)
        for name in SPLITS:
            header = f"{name} objects of {sources}: seed {seed}, test {test:g}, val {val:g} (datagen objects split)"
            _write_text(folder / f"{name}.txt", split_listing(split.sets[name], folder, header))
        rows: list[list[Cell]] = [
            [stratum, *(str(counts[name]) for name in SPLITS)] for stratum, counts in sorted(split.strata.items())
        ]
        rows.append(["all meshes", *(str(sum(c[name] for c in split.strata.values())) for name in SPLITS)])
        rows.append(["all lines", *(str(len(split.sets[name])) for name in SPLITS)])
        say(f"wrote {out}/{{train,val,test}}.txt; {len(split.held)} lines held out by --hold")
        print_rows(["stratum", *SPLITS], rows)


def relative_path_text(path: Path, folder: Path) -> str:
    from datagen.pipeline.objects.objects_file import relative_path

    return relative_path(path.absolute(), folder)


def _mesh_check(config: GenerationConfig) -> MeshCheck:
    """``objects scan --check``: the one-line reason a mesh file cannot be made into an object, or the
    warning `objects show` gives a mesh that can (a flat one)."""
    from datagen.pipeline.objects.prepare import prepare_object
    from datagen.pipeline.objects.scan import Verdict
    from datagen.pipeline.objects.spec import ObjectOptions, ObjectSpec

    def check(path: Path) -> Verdict:
        spec = ObjectSpec(source=str(path), name=path.stem, options=ObjectOptions(), object_id="")
        try:
            prepared = prepare_object(spec, config)
        except DatagenError as error:
            return Verdict(refused=str(error).removeprefix(f"{path}: "))
        flat = prepared.flat_warning()
        return Verdict(warning=flat.removeprefix(f"{path.stem}: ") if flat else None)

    return check


def _write_text(path: Path, text: str) -> None:
    """Write through a hidden temporary sibling and rename, creating the folder; `OutputError` on failure."""
    if path.is_dir():
        raise OutputError(f"{path}: is a folder; give --out a file path, e.g. {path / 'variants.txt'}")
    temporary = path.with_name(f".{path.name}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary.write_bytes(text.encode("utf-8"))
        temporary.replace(path)
    except OSError as exc:
        reason = exc.strerror or exc
        raise OutputError(f"{path}: cannot write the objects file ({reason}); choose another --out") from None


def scan(
    objects: Annotated[Path, typer.Option("--objects", "-o", help="Objects file.")],
    config: ConfigOption = None,
    rotations: Annotated[
        str, typer.Option(help="'all' for every rotation of the config, or one rotation index.")
    ] = "all",
) -> None:
    """Prepare, sample P_gt and image every task (object x rotation) from every view.

    Steps 0-3 of the pipeline alone (no refinement, labels or dataset): a quick look at what each
    view of each object sees before a `datagen submit`.
    """
    import numpy as np

    from datagen.config_io import load_config
    from datagen.pipeline.objects.objects_file import read_objects_file
    from datagen.pipeline.objects.prepare import prepare_object
    from datagen.pipeline.scanning import scan_task
    from datagen.pipeline.thread_limits import single_threaded_blas
    from datagen.pipeline.viewspace import build_view_space

    with user_errors(), single_threaded_blas():
        resolved = load_config(config)
        view_space = build_view_space(resolved.view_space)
        listing = read_objects_file(objects)
        chosen = _rotations(rotations, resolved.rotations)
        table = Table(
            "object",
            "rot",
            "P_gt",
            "union V",
            "keys/view",
            "only-1-view",
            "rays",
            "s",
            title=f"{resolved.imaging} imaging, {view_space.count} views",
        )
        problems: list[str] = [str(error) for error in listing.errors]
        started = time.perf_counter()
        with IntervalProgress(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeRemainingColumn(),
            console=console,
            transient=True,
        ) as progress:
            bar = progress.add_task("scanning", total=len(listing.objects) * len(chosen))
            for spec in listing.objects:
                try:
                    prepared = prepare_object(spec, resolved)
                except DatagenError as exc:
                    problems.append(f"{spec.origin}: {exc}")
                    progress.advance(bar, len(chosen))
                    continue
                for rotation in chosen:
                    progress.update(bar, description=f"{spec.name} r{rotation}")
                    result = scan_task(prepared, rotation, resolved, view_space)
                    visible = result.visible_keys()
                    keys, counts = np.unique(np.concatenate(visible), return_counts=True)
                    single = set(keys[counts == 1].tolist())
                    table.add_row(
                        spec.name,
                        str(rotation),
                        str(len(result.ground_truth)),
                        str(keys.size),
                        str(int(statistics.median(len(v) for v in visible))),
                        str(int(statistics.median(len(single.intersection(v.tolist())) for v in visible))),
                        str(result.rays_cast),
                        f"{result.seconds:.2f}",
                    )
                    progress.advance(bar)
        print_table(table)
        console.print(f"{plural(table.row_count, 'task')} in {time.perf_counter() - started:.1f} s")
        for problem in problems:
            console.print(Text("error: ", style="red") + Text(problem), highlight=False)
        if problems:
            raise typer.Exit(1)


def _rotations(text: str, total: int) -> list[int]:
    if text == "all":
        return list(range(total))
    if text.isdigit() and int(text) < total:
        return [int(text)]
    raise DatagenError(f"--rotations {text!r}: use 'all' or a rotation index 0..{total - 1}")
