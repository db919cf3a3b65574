"""Benchmark: what a trainer's machine installs (`./reader ./osvp`) against the full install.

Each install goes into a fresh virtual environment, torch first and pinned (as the README says),
then the checkout's distributions in one resolve, non-editable. Printed per install: seconds for
torch, seconds for the rest, the distributions installed, and the size on disk of site-packages with
and without torch. The full install is the baseline, measured in the same run.

    python -m benchmarks.reading.light_install [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from benchmarks.common import REPO_ROOT

REPO = REPO_ROOT
TORCH = "torch==2.13.0"
INSTALLS = {
    "full (reader + datagen + osvp)": [str(REPO / "reader"), str(REPO), str(REPO / "osvp")],
    "light (reader + osvp)": [str(REPO / "reader"), str(REPO / "osvp")],
}
TORCH_PARTS = ("torch", "nvidia", "triton", "functorch", "torchgen")
"""site-packages entries that are torch's (its CPU build ships no nvidia or triton, the CUDA one does)."""


@dataclass(frozen=True)
class Measured:
    name: str
    torch_seconds: float
    rest_seconds: float
    distributions: int
    size_mb: float
    size_without_torch_mb: float
    heavy: tuple[str, ...]


def folder_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink()) / 1e6


def timed_pip(python: Path, *arguments: str) -> float:
    start = time.perf_counter()
    command = [sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-input", *arguments]
    subprocess.run(command, check=True)
    return time.perf_counter() - start


def measure(name: str, projects: list[str], folder: Path) -> Measured:
    venv = folder / name.split()[0]
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    for project in ("reader", "osvp", ""):
        shutil.rmtree(REPO / project / "build", ignore_errors=True)  # pip builds in the project's folder
    torch_seconds = timed_pip(python, TORCH)
    rest_seconds = timed_pip(python, *projects)
    listed = subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "list", "--format", "json"],
        check=True,
        capture_output=True,
        text=True,
    )
    names = sorted(entry["name"].lower() for entry in json.loads(listed.stdout))
    (site,) = sorted((venv / "lib").glob("python3*/site-packages"))
    torch_mb = sum(folder_mb(p) for p in site.iterdir() if p.name.split("-")[0] in TORCH_PARTS and p.is_dir())
    total = folder_mb(site)
    generator = ("ray", "embreex", "trimesh", "highspy", "open3d", "manifold3d")
    return Measured(
        name,
        torch_seconds,
        rest_seconds,
        len(names),
        total,
        total - torch_mb,
        tuple(n for n in names if n in generator),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keep", type=Path, help="build the environments here and keep them")
    args = parser.parse_args()
    folder = args.keep or Path(tempfile.mkdtemp(prefix="light-install-"))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        results = [measure(name, projects, folder) for name, projects in INSTALLS.items()]
    finally:
        if args.keep is None:
            shutil.rmtree(folder, ignore_errors=True)
    base = results[0]
    print(f"{'install':32} {'torch s':>8} {'rest s':>7} {'dists':>6} {'MB':>7} {'MB w/o torch':>13}  generator parts")
    for r in results:
        print(
            f"{r.name:32} {r.torch_seconds:8.1f} {r.rest_seconds:7.1f} {r.distributions:6d} {r.size_mb:7.0f} "
            f"{r.size_without_torch_mb:13.0f}  {', '.join(r.heavy) or 'none'}"
        )
    for r in results[1:]:
        print(
            f"{r.name} / {base.name}: rest {r.rest_seconds / base.rest_seconds:.2f}x time, "
            f"{r.size_without_torch_mb / base.size_without_torch_mb:.2f}x size without torch, "
            f"{r.size_mb / base.size_mb:.2f}x size with torch"
        )


if __name__ == "__main__":
    main()
