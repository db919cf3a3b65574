"""Real meshes in POCO's training pool (`datagen poco train --objects`).

An objects file's watertight meshes join the pool under their listed names; an open mesh (no inside,
so no labels), a built-in (already a training shape), a corrupt mesh and an unreadable line are each
left out with one line saying why. The labels of a joined sphere are checked against the analytic inside of the
sphere fitted to its observed surface.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

pytest.importorskip("torch")

from datagen.training.poco_samples import generate_pool, objects_file_specs
from schemas.config import GenerationConfig


@pytest.fixture
def listing(tmp_path: Path) -> Path:
    trimesh.creation.icosphere(subdivisions=4, radius=0.04).export(tmp_path / "ball.ply")
    open_box = trimesh.creation.box(extents=(0.08, 0.06, 0.05))
    open_box.update_faces(np.arange(len(open_box.faces)) > 1)  # one side removed
    open_box.export(tmp_path / "open_box.ply")
    (tmp_path / "broken.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n0 0\n")
    text = "ball.ply name=scan-ball\nopen_box.ply\nbuiltin:mug\nmissing.ply\nbroken.ply\n"
    (tmp_path / "objects.txt").write_text(text)
    return tmp_path / "objects.txt"


def test_only_watertight_meshes_join_and_each_other_line_says_why(listing: Path) -> None:
    listed = objects_file_specs(listing)
    assert [name for name, _, _ in listed.kept] == ["scan-ball"]
    _, source, data = listed.kept[0]
    assert Path(source) == listing.parent / "ball.ply" and data == Path(source).read_bytes()
    reasons = "\n".join(listed.left_out)
    assert len(listed.left_out) == 4
    assert "open_box: open mesh" in reasons
    assert "mug: a built-in" in reasons
    assert "missing.ply" in reasons
    assert "broken.ply" in reasons


def test_a_joined_mesh_is_labelled_by_its_inside(listing: Path) -> None:
    pool = generate_pool(objects_file_specs(listing).kept, tasks=1, samples_per_task=2, seed=3)
    assert pool and {sample.shape for sample in pool} == {"scan-ball"}
    for sample in pool:
        centre, radius = fitted_sphere(sample.inputs.astype(np.float64))
        distance = np.linalg.norm(sample.queries - centre, axis=1)
        # key centres lie within half a voxel's diagonal of the surface: judge those clear of it
        clear = np.abs(distance - radius) > 2 * GenerationConfig().voxel_size
        assert clear.sum() > 100 and 0 < sample.labels.mean() < 1
        np.testing.assert_array_equal(sample.labels[clear], (distance < radius)[clear])


def fitted_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere through points: |p|^2 = 2 c.p + (r^2 - |c|^2), linear in c and the constant."""
    design = np.column_stack([2 * points, np.ones(len(points))])
    solution, *_ = np.linalg.lstsq(design, (points**2).sum(axis=1), rcond=None)
    centre = solution[:3]
    return centre, float(np.sqrt(solution[3] + centre @ centre))
