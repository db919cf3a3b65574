"""Check: the authors' unmodified trainers read each export layout and train one epoch on a CPU.

    python -m studies.labels.authors_trainers --authors CLONE --work NEW_DIR
        [--url DATASET] [--objects capsule,cone,l_bracket] [--rotations 2] [--only NAME,...]
        [--out studies/labels/results/authors-trainers.md --replace]

1. Builds a small dataset with ``datagen submit`` (built-in objects, refiner none, ``--rotations``
   rotations; local Ray), unless ``--url`` names one.
2. Exports it with ``datagen shards export`` in each layout a trainer reads (mascvp, nbvnet, pcnbv).
3. Copies each trainer folder of psc0628/MA-SCVP's ``Networks_pytorch`` (``--authors``: a clone; their
   code is never part of this repository) to ``WORK/trainers/``, links the export's files where the
   trainer opens them, and runs its ``train.py`` for one epoch through ``authors_standins/launch.py``
   (docs/authors-code.md sections 7.3-7.5 say what each needed), recording what its loaders read
   and every loss it back-propagated.
4. Checks by sha256 that every file of theirs in each copy is byte for byte the clone's, after the run.
5. Writes the results: the exact commands, exit codes, what each loader read, the losses, to
   ``WORK/authors-trainers.md`` or ``--out`` (a committed result is written over only with ``--replace``).

``--work`` must be a new or empty folder: the harness writes only there and deletes nothing it did not make.

The stand-ins on PYTHONPATH (``authors_standins/``) are the only code added: torchvision's ``Compose``
where torchvision is not installed, and PC-NBV's unreleased ``dataset.dataset`` loader.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import json
import os
import platform
import re
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from benchmarks.common import REPO_ROOT, add_report_options, check_new_folder, check_report

STANDINS = Path(__file__).resolve().parent / "authors_standins"
LAUNCHER = STANDINS / "launch.py"
RESULT = REPO_ROOT / "studies" / "labels" / "results" / "authors-trainers.md"
"""The committed result (``--out`` it with ``--replace`` to update it)."""
NETWORKS = "Networks_pytorch"
VAL = 0.34
TIMEOUT_S = 3600
ANSI = re.compile(r"\x1b\[[0-9;]*m")


@dataclass(frozen=True)
class Launch:
    """How one trainer is started: its own arguments, the launcher's overrides, extra PYTHONPATH folders
    and the links made to the export's files."""

    args: list[str] = field(default_factory=list)
    set_module: list[str] = field(default_factory=list)
    set_global: list[str] = field(default_factory=list)
    pythonpath: list[Path] = field(default_factory=list)
    links: list[tuple[Path, Path]] = field(default_factory=list)


@dataclass(frozen=True)
class Trainer:
    name: str
    folder: str
    """Below the clone's ``Networks_pytorch``."""
    layout: str
    prepare: Callable[[Path, Path, dict[str, Any]], Launch]
    """(copy of their folder, the export, the export's provenance) -> how to start it."""
    shows: str
    """A regex of the output lines worth quoting (their own loss or accuracy prints)."""
    preload: tuple[str, ...] = ()
    """Diagnostic patches (``authors_standins/patches``): a run with any is not of their code unmodified."""
    control: str | None = None
    """Python run in their copy when the trainer fails: does the failure happen without our data?"""


def _link(link: Path, target: Path) -> tuple[Path, Path]:
    link.parent.mkdir(parents=True, exist_ok=True)
    if link.is_symlink() or link.exists():
        link.unlink()
    link.symlink_to(target)
    return link, target


def _nbvnet(run: Path, export: Path, provenance: dict[str, Any]) -> Launch:
    """train.py opens ./grids.npy, ./labels.npy and ./points_in_sphere.txt and hard-codes ``epochs = 1000``."""
    links = [
        _link(run / "grids.npy", export / "train" / "grids.npy"),
        _link(run / "labels.npy", export / "train" / "labels.npy"),
        _link(run / "points_in_sphere.txt", export / "points_in_sphere.txt"),
    ]
    return Launch(set_global=["epochs=1"], links=links)


def _ma_scvp(run: Path, export: Path, provenance: dict[str, Any]) -> Launch:
    """config.py names the grid file (vss and label paths replace 'grid' in it) and the epochs; the shipped
    NET_TYPE is "SCVP", which ignores the view state: "MASCVP" is the network that reads it."""
    grid = json.dumps(str(export / "train" / "grid.npy"))
    return Launch(set_module=[f"config.GRID_PATH={grid}", "config.NUM_EPOCHS=1", 'config.NET_TYPE="MASCVP"'])


def _sc_net(run: Path, export: Path, provenance: dict[str, Any]) -> Launch:
    """train.py reads ../data/SC_NPY/grids_LM1.npy and labels_LM1.npy; --epochs is its own option."""
    data = run.parent / "data" / "SC_NPY"
    links = [
        _link(data / "grids_LM1.npy", export / "train" / "grid.npy"),
        _link(data / "labels_LM1.npy", export / "train" / "label.npy"),
    ]
    return Launch(args=["--epochs", "1"], links=links)


def _pc_nbv(run: Path, export: Path, provenance: dict[str, Any]) -> Launch:
    """train.py opens ./dataset/<four names>_{train,test}.pt through ``dataset.dataset.ShapeNet3`` (not
    released: a stand-in on PYTHONPATH); its options give the epochs and the loader workers. Its
    BatchNorm layers cannot train on a batch of one, so the batch size avoids a last batch of one."""
    links = [_link(run / "dataset" / p.name, p) for p in sorted((export / "dataset").glob("*.pt"))]
    train = provenance["arrays"]["dataset/accumulate_pointclouds_train.pt"]["shape"][0]
    batch = 32 if train % 32 != 1 else 31
    args = ["--epochs", "1", "--num_workers", "0", "--batch_size", str(batch)]
    return Launch(args=args, pythonpath=[STANDINS / "pcnbv"], links=links)


SC_NET_CONTROL = """
import torch, model
net = model.MyNBVNetV3()
loss = net(torch.rand(2, 1, 32, 32, 32)).sum()
loss.backward()
print("their model trains on random input")
"""
"""SC-Net's own network, one step on random grids: shows whether its failure needs our data at all."""

TRAINERS = {
    trainer.name: trainer
    for trainer in (
        Trainer("nbv-net-master", "nbv-net-master", "nbvnet", _nbvnet, r"^Epoch: |^len\(dataset\)"),
        Trainer("ma_scvp", "ma_scvp", "mascvp", _ma_scvp, r"^epoch : |^Loss : |loss=tensor"),
        Trainer(
            "sc-net",
            "sc-net",
            "mascvp",
            _sc_net,
            r"^len\(dataset\)|^epoch : |^test accuracy|loss=tensor",
            control=SC_NET_CONTROL,
        ),
        Trainer(
            "sc-net-residual-patch",
            "sc-net",
            "mascvp",
            _sc_net,
            r"^len\(dataset\)|^epoch : |^test accuracy|loss=tensor",
            preload=("scnet_residual",),
        ),
        Trainer("PC-NBV_pytorch", "PC-NBV_pytorch", "pcnbv", _pc_nbv, r"Training epoch|Validation epoch|Best model"),
    )
}


# -- running commands ----------------------------------------------------------------------------------


@dataclass
class Ran:
    command: str
    exit: int
    seconds: float
    output: str


def run(command: list[str], cwd: Path, env: dict[str, str], shown_env: dict[str, str], log: Path) -> Ran:
    started = time.perf_counter()
    with log.open("w") as handle:
        done = subprocess.run(command, cwd=cwd, env=env, stdout=handle, stderr=subprocess.STDOUT, timeout=TIMEOUT_S)
    seconds = time.perf_counter() - started
    prefix = " ".join(f"{k}={shlex.quote(v)}" for k, v in shown_env.items())
    shown = f"cd {shlex.quote(str(cwd))} && {prefix + ' ' if prefix else ''}{shlex.join(command)}"
    text = log.read_text(errors="replace")
    print(f"  exit {done.returncode} in {seconds:.0f} s: {shlex.join(command)[:160]}", flush=True)
    return Ran(shown, done.returncode, seconds, text)


def datagen_env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(REPO_ROOT))


def datagen(args: list[str], work: Path, log: Path) -> Ran:
    command = [sys.executable, "-m", "datagen.cli.main", *args]
    return run(command, REPO_ROOT, datagen_env(), {"PYTHONPATH": str(REPO_ROOT)}, log)


def build_dataset(work: Path, objects: list[str], rotations: int) -> tuple[str, Ran]:
    build = work / "build"
    build.mkdir(parents=True, exist_ok=True)
    (build / "objects.txt").write_text("".join(f"builtin:{name}\n" for name in objects))
    (build / "config.toml").write_text(f'rotations = {rotations}\nrefiner = "none"\n')
    url = str(work / "dataset")
    args = ["submit", "--objects", str(build / "objects.txt"), "--config", str(build / "config.toml")]
    ran = datagen([*args, "--out", url, "--home", str(build / "home"), "--workers", "2"], work, build / "submit.log")
    return url, ran


# -- the authors' files ----------------------------------------------------------------------------------


def sha256s(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and not p.is_symlink()
    }


def git_state(authors: Path) -> dict[str, str]:
    def git(*args: str) -> str:
        done = subprocess.run(["git", "-C", str(authors), *args], capture_output=True, text=True)
        return done.stdout.strip() if done.returncode == 0 else ""

    return {
        "commit": git("rev-parse", "HEAD"),
        "remote": git("remote", "get-url", "origin"),
        "dirty": git("status", "--porcelain"),
    }


def run_trainer(trainer: Trainer, authors: Path, work: Path, export: Path) -> dict[str, Any]:
    source = authors / NETWORKS / trainer.folder
    theirs = sha256s(source)
    copy = work / "trainers" / trainer.name
    if copy.exists():
        shutil.rmtree(copy)
    shutil.copytree(source, copy, symlinks=True)
    provenance = json.loads((export / "provenance.json").read_text())
    launch = trainer.prepare(copy, export, provenance)
    paths = [*launch.pythonpath]
    if trainer.preload:
        paths.append(STANDINS / "patches")
    if importlib.util.find_spec("torchvision") is None:
        paths.append(STANDINS)  # torchvision's Compose stand-in, only where torchvision is absent
    shown_env = {"PYTHONPATH": os.pathsep.join(str(p) for p in paths), "MPLBACKEND": "Agg"} if paths else {}
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1", MPLBACKEND="Agg")
    env.pop("PYTHONPATH", None)
    env.update(shown_env)
    probe = work / "probes" / f"{trainer.name}.json"
    probe.parent.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, str(LAUNCHER), "--script", str(copy / "train.py"), "--probe", str(probe)]
    for item in launch.set_module:
        command += ["--set-module", item]
    for item in launch.set_global:
        command += ["--set-global", item]
    for item in trainer.preload:
        command += ["--preload", item]
    command += ["--", *launch.args]
    print(f"{trainer.name}: one epoch on {trainer.layout} ...", flush=True)
    ran = run(command, copy, env, shown_env, work / "probes" / f"{trainer.name}.log")
    control = None
    if ran.exit and trainer.control is not None:
        control = run([sys.executable, "-c", trainer.control], copy, env, shown_env, work / "probes" / "control.log")
    after = sha256s(copy)
    changed = sorted(name for name, digest in theirs.items() if after.get(name) != digest)
    added = sorted(set(after) - set(theirs))
    found = json.loads(probe.read_text()) if probe.exists() else {}
    pattern = re.compile(trainer.shows)
    lines = [ANSI.sub("", line).strip() for line in re.split(r"[\r\n]+", ran.output)]
    return {
        "trainer": trainer,
        "ran": ran,
        "control": control,
        "probe": found,
        "shown": [line for line in lines if pattern.search(line)][-6:],
        "tail": [line for line in lines if line][-6:],
        "files": len(theirs),
        "changed": changed,
        "added": added,
        "links": [(str(link.relative_to(work)), str(target)) for link, target in launch.links],
    }


def their_fault(result: dict[str, Any]) -> bool:
    """Whether a failed run fails the same way on random input, without our data."""
    control = result["control"]
    if control is None or not control.exit:
        return False
    error = (result["probe"].get("error") or "").split(":", 1)[0]
    return bool(error) and error in control.output


# -- report ------------------------------------------------------------------------------------------------


def _loss_summary(losses: list[float]) -> str:
    if not losses:
        return "none recorded"
    mean = sum(losses) / len(losses)
    return f"{len(losses)} steps: first {losses[0]:.4g}, last {losses[-1]:.4g}, mean {mean:.4g}"


def _loaders(probe: dict[str, Any]) -> list[str]:
    rows = []
    for loader in probe.get("loaders", []):
        rows.append(
            f"  - `{loader['dataset']}` of {loader['dataset_len']} samples ({loader['sampler']}, batch "
            f"{loader['batch_size']}): {loader['passes']} passes, {loader['batches']} batches, "
            f"{loader['samples']} samples; first batch {json.dumps(loader['first_batch'])}"
        )
    return rows


def _control_lines(result: dict[str, Any]) -> list[str]:
    control = result["control"]
    if control is None:
        return []
    last = [line for line in control.output.splitlines() if line.strip()][-1:] or ["(no output)"]
    verdict = "the same failure without our data: theirs" if their_fault(result) else "not reproduced"
    code = (result["trainer"].control or "").strip().splitlines()
    return [
        f"- Control: their network alone on random input, `python -c` in their copy (exit {control.exit}, {verdict}):",
        "",
        "```python",
        *code,
        "```",
        "",
        f"  -> `{last[0]}`",
    ]


def report(
    args: argparse.Namespace,
    state: dict[str, str],
    built: Ran | None,
    url: str,
    exports: dict[str, tuple[Ran, dict[str, Any]]],
    results: list[dict[str, Any]],
) -> str:
    import torch

    out = [
        "# The authors' trainers on our exports, one epoch on a CPU",
        "",
        "Written by `python -m studies.labels.authors_trainers` (see its docstring and docs/authors-code.md",
        "sections 7.3-7.5). Each trainer is psc0628/MA-SCVP's own folder, copied unchanged (sha256 checked",
        "after the run); the only added code is `studies/labels/authors_standins/` on PYTHONPATH.",
        "",
        f"- Authors' code: psc0628/MA-SCVP, clone `{args.authors}` (origin `{state['remote']}`) at "
        f"`{state['commit'][:7]}`"
        f"{' (clean)' if not state['dirty'] else ' (NOT clean: ' + state['dirty'].replace(chr(10), '; ') + ')'}",
        f"- Machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
        f"torch {torch.__version__}, no GPU used; torchvision "
        f"{'installed' if importlib.util.find_spec('torchvision') else 'absent (stand-in)'}",
        "",
        "## Dataset and exports",
        "",
    ]
    if built is not None:
        out += [f"- Built (exit {built.exit}, {built.seconds:.0f} s): `{built.command}`"]
    else:
        out += [f"- Dataset given: `{url}`"]
    for layout, (ran, provenance) in exports.items():
        skipped = {k: v for k, v in provenance.get("skipped", {}).items() if k != "samples"}
        arrays = "; ".join(
            f"{path} {tuple(info['shape'])} {info['dtype']}" for path, info in provenance.get("arrays", {}).items()
        )
        out += [
            f"- `{layout}` (exit {ran.exit}, {ran.seconds:.0f} s): `{ran.command}`",
            f"  - written {provenance.get('written')} of {provenance.get('dataset', {}).get('samples')} samples, "
            f"skipped {skipped}, train_split {provenance.get('split', {}).get('train_split')}, test_split "
            f"{provenance.get('split', {}).get('test_split')}",
            f"  - arrays: {arrays}",
        ]
    out += ["", "## Trainers", ""]
    out += ["| trainer | layout | run | exit | seconds | training loss (probe) | their files unchanged |"]
    out += ["|---|---|---|---|---|---|---|"]
    for result in results:
        trainer, ran = result["trainer"], result["ran"]
        unchanged = "yes" if not result["changed"] else f"NO: {', '.join(result['changed'])}"
        how = f"patched ({', '.join(trainer.preload)}), diagnostic" if trainer.preload else "unmodified"
        out.append(
            f"| {trainer.name} | {trainer.layout} | {how} | {ran.exit} | {ran.seconds:.0f} | "
            f"{_loss_summary(result['probe'].get('losses', []))} | {unchanged} ({result['files']} files) |"
        )
    for result in results:
        trainer, ran, probe = result["trainer"], result["ran"], result["probe"]
        out += [
            "",
            f"### {trainer.name}",
            "",
            f"- Command: `{ran.command}`",
            f"- Exit code {ran.exit}{', error: ' + probe['error'] if probe.get('error') else ''}; {ran.seconds:.0f} s",
            *_control_lines(result),
            *(
                [f"- Diagnostic patch preloaded (NOT their code unmodified): {', '.join(trainer.preload)}"]
                if trainer.preload
                else []
            ),
            "- Linked: " + (", ".join(f"`{link}` -> `{target}`" for link, target in result["links"]) or "nothing"),
            "- What its loaders read:",
            *_loaders(probe),
            f"- Losses back-propagated: {_loss_summary(probe.get('losses', []))}",
            f"- CUDA-only extensions imported: {probe.get('cuda_extensions_imported') or 'none'}",
            f"- Their {result['files']} files after the run: "
            + ("all byte-identical to the clone (sha256)" if not result["changed"] else f"CHANGED {result['changed']}"),
            f"- Files the run added in its copy: {', '.join(result['added']) or 'none'}",
            "- Their output (quoted lines):",
            "",
            "```",
            *(result["shown"] or result["tail"]),
            "```",
        ]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--authors", type=Path, required=True, help="A clone of psc0628/MA-SCVP.")
    parser.add_argument("--work", type=Path, required=True, help="A new or empty scratch folder.")
    parser.add_argument("--url", help="Export this dataset instead of building one.")
    parser.add_argument("--objects", default="capsule,cone,l_bracket", help="Built-in objects of the dataset.")
    parser.add_argument("--rotations", type=int, default=2)
    parser.add_argument("--only", help="Comma-separated trainer names (default: all).")
    add_report_options(parser, None, f"the report (default WORK/authors-trainers.md; committed: {RESULT.name})")
    args = parser.parse_args(argv)
    check_new_folder(parser, args.work)
    args.out = args.out or args.work / "authors-trainers.md"
    check_report(parser, args.out, args.replace)
    if not (args.authors / NETWORKS).is_dir():
        raise SystemExit(f"{args.authors}: no {NETWORKS} folder; clone psc0628/MA-SCVP there or pass --authors")
    chosen = [TRAINERS[name] for name in args.only.split(",")] if args.only else list(TRAINERS.values())
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    state = git_state(args.authors)
    built = None
    url = args.url
    if url is None:
        print("building the dataset ...", flush=True)
        url, built = build_dataset(work, args.objects.split(","), args.rotations)
        if built.exit:
            raise SystemExit(f"datagen submit failed:\n{built.output[-3000:]}")
    exports: dict[str, tuple[Ran, dict[str, Any]]] = {}
    for layout in sorted({trainer.layout for trainer in chosen}):
        target = work / "exports" / layout
        target.parent.mkdir(parents=True, exist_ok=True)
        args_ = ["shards", "export", url, str(target), "--layout", layout, "--val", str(VAL)]
        ran = datagen(args_, work, work / "exports" / f"{layout}.log")
        if ran.exit:
            raise SystemExit(f"export {layout} failed:\n{ran.output[-3000:]}")
        exports[layout] = (ran, json.loads((target / "provenance.json").read_text()))
    results = [run_trainer(t, args.authors.resolve(), work, work / "exports" / t.layout) for t in chosen]
    args.out.write_text(report(args, state, built, url, exports, results))
    print(f"wrote {args.out}")
    failed = [r["trainer"].name for r in results if (r["ran"].exit and not their_fault(r)) or r["changed"]]
    if failed:
        raise SystemExit(f"failed or edited: {', '.join(failed)}")


if __name__ == "__main__":
    main()
