"""The compose cluster for real (docker-compose.yml, built and started by scripts/cluster-up.sh):
`scripts/cluster-faults.sh` submits a job from this host to the Ray head's client port with the
dataset on the cluster's SeaweedFS, then kills a worker container, restarts the head and the S3
server mid-job, and takes the whole cluster down and up; every dataset must validate and carry the
digest of a local run of the same job.

It runs only where the cluster can: a container engine (podman, or a Docker engine), the images
built (`bash scripts/cluster-up.sh` once, several minutes) and a .env with the cluster's credentials.
Elsewhere (CI among them: no container engine) it skips at once with the reason. It takes several
minutes; `-m "not cluster"` leaves it out.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
JOBS = ("submit", "worker", "driver", "head", "s3")
CASES = ("local", *JOBS, *(f"down-up:{job}" for job in JOBS))

pytestmark = [pytest.mark.cluster, pytest.mark.slow]


def _env_value(name: str, default: str) -> str:
    env_file = REPO_ROOT / ".env"
    for line in env_file.read_text().splitlines():
        key, separator, value = line.strip().partition("=")
        if separator and key == name:
            return value.strip()
    return default


def _why_not() -> str | None:
    """Why the cluster cannot run here (None when it can); a few cheap checks, no container starts."""
    engine = shutil.which("podman")
    if engine is None:
        docker = shutil.which("docker")
        ok = docker is not None and subprocess.run([docker, "info"], capture_output=True, timeout=20).returncode == 0
        if not ok:
            return "no podman and no Docker engine on this machine (the compose cluster needs one)"
        engine = docker
    if not (REPO_ROOT / ".env").exists():
        return "no .env (copy .env.example to .env and set S3_SECRET_KEY; scripts/cluster-up.sh)"
    for image in (_env_value("DATAGEN_IMAGE", "datagen:local"), _env_value("S3_IMAGE", "datagen-seaweedfs:local")):
        found = subprocess.run([engine, "image", "inspect", image], capture_output=True, timeout=30).returncode == 0
        if not found:
            return f"image {image} is not built (bash scripts/cluster-up.sh builds it, several minutes)"
    return None


def test_job_and_faults_on_the_compose_cluster(tmp_path: Path) -> None:
    reason = _why_not()
    if reason is not None:
        pytest.skip(reason)
    result = subprocess.run(
        ["bash", "scripts/cluster-faults.sh", str(tmp_path / "check")],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=3600,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )
    rows = [line.split("\t") for line in result.stdout.splitlines() if line.startswith("RESULT\t")]
    outcomes = {row[1]: row[3] for row in rows}
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-4000:]
    assert sorted(outcomes) == sorted(CASES), outcomes
    reference = {row[1]: row[4] for row in rows}["local"]
    assert [name for name, row in outcomes.items() if name != "local" and not row.startswith("complete")] == []
    assert {row[4] for row in rows} == {reference}, rows
