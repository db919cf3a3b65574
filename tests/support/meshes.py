"""The real meshes of ../shared/meshes (or DATAGEN_SHARED_MESHES): paths, and a skip mark for when they are absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
SHARED_MESHES = Path(os.environ.get("DATAGEN_SHARED_MESHES", REPO_ROOT.parent / "shared" / "meshes"))
MESH_SUFFIXES = {".obj", ".ply", ".stl", ".off", ".glb"}


def shared_mesh_paths() -> list[Path]:
    """Every real mesh of ../shared/meshes, sorted; empty when the folder is absent."""
    if not SHARED_MESHES.is_dir():
        return []
    return sorted(p for p in SHARED_MESHES.iterdir() if p.suffix.lower() in MESH_SUFFIXES)


requires_shared_meshes = pytest.mark.skipif(
    not shared_mesh_paths(), reason=f"real meshes not found at {SHARED_MESHES} (../shared/meshes)"
)
