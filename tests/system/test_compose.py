"""The cluster's deployment files (docker-compose.yml, its podman override, Dockerfile, .env.example) checked as data: a
mistake here (a port open to the network, a worker built from another image than the head, a secret
committed, a service nobody health-checks) shows up only on someone's cluster otherwise. When the
Docker CLI has its compose plugin, `docker compose config` validates the file as Docker reads it.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tomllib
from pathlib import Path
from typing import Any

import pytest
import yaml

REPO_ROOT = Path(__file__).resolve().parents[2]
COMPOSE_FILE = REPO_ROOT / "docker-compose.yml"
PODMAN_OVERRIDE = REPO_ROOT / "docker-compose.podman.yml"
DOCKERFILE = REPO_ROOT / "Dockerfile"
ENV_EXAMPLE = REPO_ROOT / ".env.example"
LOOPBACK_PORT_PREFIX = "${BIND_ADDRESS:-127.0.0.1}:"
CLUSTER_SERVICES = ("head", "worker")
SECRET_NAME = re.compile(r"PASSWORD|SECRET|TOKEN|_KEY", re.IGNORECASE)
REAL_LOOKING_SECRETS = (
    re.compile(r"\b(AKIA|ASIA)[0-9A-Z]{16}\b"),  # an AWS access key id
    re.compile(r"[A-Za-z0-9/+=]{32,}"),  # a long random token (an AWS secret key is 40 such characters)
)


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    data = yaml.safe_load(COMPOSE_FILE.read_text())
    assert isinstance(data, dict) and isinstance(data.get("services"), dict)
    return data


@pytest.fixture(scope="module")
def env_example() -> dict[str, str]:
    """KEY=VALUE lines of .env.example (comments and blank lines skipped)."""
    values = {}
    for line in ENV_EXAMPLE.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        key, separator, value = line.partition("=")
        assert separator, f".env.example: not KEY=VALUE: {line!r}"
        values[key.strip()] = value.strip()
    return values


def services(compose: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return dict(sorted(compose["services"].items()))


def is_one_shot(service: dict[str, Any]) -> bool:
    """A run-to-completion service (the bucket creator): it is never restarted."""
    return str(service.get("restart", "no")) == "no"


def command_text(service: dict[str, Any]) -> str:
    command = service.get("command", "")
    return " ".join(command) if isinstance(command, list) else str(command)


def test_compose_parses_with_the_expected_services(compose: dict[str, Any]) -> None:
    assert sorted(compose["services"]) == ["head", "s3", "worker"]
    one_shot = sorted(name for name, service in services(compose).items() if is_one_shot(service))
    assert one_shot == []  # the S3 server creates its own bucket


def test_healthchecks_are_shell_strings(compose: dict[str, Any]) -> None:
    """podman-compose 1.0.3 turns a list-form test into one quoted word, and pops its first item on
    the first replica (the second worker then fails to start): every test is a CMD-SHELL string."""
    lists = sorted(
        name for name, service in services(compose).items() if not isinstance(service["healthcheck"]["test"], str)
    )
    assert lists == []


def test_podman_override_only_adds_what_podman_needs(compose: dict[str, Any]) -> None:
    override = yaml.safe_load(PODMAN_OVERRIDE.read_text())
    assert set(override["services"]) <= set(compose["services"])
    # no ports, no environment, no image: podman-compose appends lists and the rest must stay as Docker has it
    added = sorted({key for service in override["services"].values() for key in service})
    assert added == ["pull_policy"]


def test_every_long_running_service_has_a_healthcheck(compose: dict[str, Any]) -> None:
    missing = sorted(
        name
        for name, service in services(compose).items()
        if not is_one_shot(service) and not (service.get("healthcheck") or {}).get("test")
    )
    assert missing == []


def test_head_and_workers_share_one_image_and_build(compose: dict[str, Any]) -> None:
    head, worker = (compose["services"][name] for name in CLUSTER_SERVICES)
    assert head.get("image") and head["image"] == worker["image"]
    assert head.get("build") and head["build"] == worker["build"]
    assert head["environment"] == worker["environment"]  # the same store, reached the same way


def test_no_port_binds_beyond_loopback_by_default(compose: dict[str, Any], env_example: dict[str, str]) -> None:
    published = sorted(
        (name, str(port)) for name, service in services(compose).items() for port in service.get("ports", [])
    )
    assert published, "no published port at all: the test would check nothing"
    assert [entry for entry in published if not entry[1].startswith(LOOPBACK_PORT_PREFIX)] == []
    assert env_example.get("BIND_ADDRESS") == "127.0.0.1"


def test_ray_services_have_shared_memory_for_the_object_store(compose: dict[str, Any]) -> None:
    assert sorted(name for name in CLUSTER_SERVICES if not compose["services"][name].get("shm_size")) == []


def test_ledger_and_s3_data_live_on_named_volumes(compose: dict[str, Any]) -> None:
    named = set(compose.get("volumes") or {})

    def named_volume_at(service: str, target: str) -> str | None:
        for entry in compose["services"][service].get("volumes", []):
            source, _, mounted = str(entry).partition(":")
            if mounted.split(":")[0] == target and source in named:
                return source
        return None

    home = compose["services"]["head"]["environment"]["DATAGEN_HOME"]
    assert named_volume_at("head", home), f"the ledger ({home}) is not on a named volume"
    assert named_volume_at("s3", "/data"), "the S3 server's data (/data) is not on a named volume"


def test_head_schedules_no_work_and_serves(compose: dict[str, Any]) -> None:
    head = command_text(compose["services"]["head"])
    assert "ray start --head" in head and "--num-cpus=0" in head, head
    assert "datagen serve" in head, head
    worker = command_text(compose["services"]["worker"])
    assert "ray start --address=head:" in worker and "--num-cpus=0" not in worker, worker


def test_env_file_is_ignored_and_the_example_holds_no_secret(
    compose: dict[str, Any], env_example: dict[str, str]
) -> None:
    patterns = {line.strip() for line in (REPO_ROOT / ".gitignore").read_text().splitlines()}
    assert patterns & {".env", "/.env"}, ".env (real credentials) is not in .gitignore"
    git = shutil.which("git")
    if git is not None and (REPO_ROOT / ".git").exists():  # git's own answer, where this is a checkout

        def ignored(name: str) -> bool:
            command = [git, "-C", str(REPO_ROOT), "check-ignore", "-q", "--no-index", name]
            result = subprocess.run(command, check=False, timeout=30)
            assert result.returncode in (0, 1), f"git check-ignore failed on {name}"
            return result.returncode == 0

        assert ignored(".env") and not ignored(".env.example")
    secrets = sorted(key for key in env_example if SECRET_NAME.search(key))
    assert secrets, "no secret-like variable in .env.example: the checks below would check nothing"
    assert [key for key in secrets if "change-me" not in env_example[key]] == []
    assert [
        (key, value) for key, value in sorted(env_example.items()) if any(p.search(value) for p in REAL_LOOKING_SECRETS)
    ] == []
    # the compose file takes every secret from the environment (.env), never literally
    literal = sorted(
        (name, key)
        for name, service in services(compose).items()
        for key, value in (service.get("environment") or {}).items()
        if SECRET_NAME.search(key) and not str(value).startswith("${")
    )
    assert literal == []


def test_dockerfile_builds_one_datagen_for_every_node() -> None:
    text = DOCKERFILE.read_text()
    assert re.search(r"^ARG BASE_IMAGE=\S+", text, re.MULTILINE), "no BASE_IMAGE build argument"
    assert re.search(r"^FROM \$\{BASE_IMAGE\}", text, re.MULTILINE)
    assert re.search(r"^ARG TORCH_INDEX=\S+", text, re.MULTILINE), "no TORCH_INDEX build argument"
    assert '--index-url "${TORCH_INDEX}"' in text
    project = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())
    packages = sorted(pattern.rstrip("*") for pattern in project["tool"]["setuptools"]["packages"]["find"]["include"])
    copied = sorted(re.findall(r"^COPY (\S+) \./\1$", text, re.MULTILINE))
    assert [package for package in packages if package not in copied] == [], "a package of pyproject is not copied"
    assert re.search(r"^COPY pyproject\.toml ", text, re.MULTILINE)
    assert re.search(r"^COPY reader \./reader$", text, re.MULTILINE), "the reader distribution is not copied"
    (extras,) = re.findall(r'pip install \./reader "\.\[([a-z0-9,]+)\]"', text)  # this checkout, as packages
    assert sorted(extras.split(",")) == sorted(
        set(extras.split(",")) & set(project["project"]["optional-dependencies"])
    )
    assert {"cluster", "s3"} <= set(extras.split(","))


def test_docker_compose_config() -> None:
    """`docker compose config` with the example environment, where a compose plugin exists."""
    docker = shutil.which("docker")
    if docker is None:
        pytest.skip("no docker CLI on this machine")
    version = subprocess.run([docker, "compose", "version"], capture_output=True, text=True, check=False, timeout=60)
    if version.returncode != 0:
        pytest.skip(f"docker compose is not available: {(version.stderr or version.stdout).strip().splitlines()[0]}")
    result = subprocess.run(
        [docker, "compose", "--env-file", str(ENV_EXAMPLE), "-f", str(COMPOSE_FILE), "config", "-q"],
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
        cwd=REPO_ROOT,
    )
    assert result.returncode == 0, result.stdout + result.stderr
