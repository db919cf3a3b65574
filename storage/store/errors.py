"""A store that cannot be reached, refuses our credentials or has no such bucket: one line, not a traceback.

Three pieces. `check_store` asks an S3 store one cheap question (HEAD of the bucket) with a short
timeout and one retry, before a command reads or writes anything, so that a wrong endpoint, key or
bucket fails in seconds with the fix named (later requests keep the full retries of
`RunSettings.storage_options`, so a store restarting mid-job is waited for). `storage_failure` turns
any store exception into a `StorageError` naming what to check. `is_store_failure` tells a failure
of the store from damage of a file (a missing chunk is damage; a refused request is not), so that
readers, `storage.validate` and `datagen shards repair` never take an unreachable store for a
damaged dataset.
"""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Iterator
from typing import Any

from storage.store.location import Location, StorageError, StoreUnreachable, first_line, is_s3

PROBE_TIMEOUT = 5.0
"""Seconds `check_store` waits to connect or for an answer (at most the configured timeout)."""
PROBE_ATTEMPTS = 2

UNREACHABLE = "unreachable"
REFUSED = "refused"
NO_BUCKET = "no bucket"

_UNREACHABLE_NAMES = (
    "EndpointConnectionError",
    "ConnectTimeoutError",
    "ReadTimeoutError",
    "ConnectionClosedError",
    "ClientConnectorError",
    "ServerDisconnectedError",
    "ServerTimeoutError",
)
_REFUSED_CODES = ("InvalidAccessKeyId", "SignatureDoesNotMatch", "AccessDenied", "Forbidden", "403", "ExpiredToken")
_NO_BUCKET_CODES = ("NoSuchBucket",)


def _chain(error: BaseException) -> Iterator[BaseException]:
    seen: set[int] = set()
    current: BaseException | None = error
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        yield current
        current = current.__cause__ or current.__context__


def _code(error: BaseException) -> str:
    """The S3 error code of a botocore ClientError ('' for other exceptions)."""
    response = getattr(error, "response", None)
    if not isinstance(response, dict):
        return ""
    return str(response.get("Error", {}).get("Code", ""))


def classify(error: BaseException) -> str | None:
    """`UNREACHABLE`, `REFUSED`, `NO_BUCKET`, or None when the error is not about the store."""
    for link in _chain(error):
        code = _code(link)
        if code in _NO_BUCKET_CODES or (code == "404" and getattr(link, "operation_name", "") == "HeadBucket"):
            return NO_BUCKET
        if code in _REFUSED_CODES or type(link).__name__ in ("NoCredentialsError", "PartialCredentialsError"):
            return REFUSED
        if type(link).__name__ in _UNREACHABLE_NAMES or isinstance(link, ConnectionError | TimeoutError):
            return UNREACHABLE
        if isinstance(link, OSError) and link.errno == errno.EREMOTEIO:  # s3fs's form of a 5xx answer
            return UNREACHABLE
        if isinstance(link, PermissionError):
            return REFUSED
    return None


def is_transient(error: BaseException) -> bool:
    """A store failure that waiting may end (unreachable, a 5xx answer), not a refusal or a missing
    bucket: what a running task waits out."""
    return classify(error) == UNREACHABLE or (classify(error) is None and is_store_failure(error))


def is_store_failure(error: BaseException) -> bool:
    """True for an error of the store itself (unreachable, refused, no bucket, a botocore or aiohttp
    error), False for a file that is missing or corrupt (damage) and for bugs."""
    if classify(error) is not None:
        return True
    # not along the chain: s3fs raises a missing object as FileNotFoundError caused by a ClientError
    return type(error).__module__.split(".")[0] in ("botocore", "aiobotocore", "aiohttp")


def storage_failure(url: str, error: BaseException) -> StoreUnreachable:
    """One line for a store that cannot be reached or refuses us, naming what to check: a
    `StoreUnreachable`, never confused with a damaged dataset (`DamagedFile`)."""
    detail = first_line(error)
    if not is_s3(url):
        return StoreUnreachable(f"{url}: cannot use the dataset store ({detail}); check the path and its permissions")
    endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL") or "AWS's default"
    kind = classify(error)
    bucket = bucket_of(url)
    if kind == UNREACHABLE:
        return StoreUnreachable(
            f"{url}: cannot reach the S3 endpoint {endpoint} ({detail}); check AWS_ENDPOINT_URL and that the "
            "server is up (the credentials AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY come next)"
        )
    if kind == REFUSED:
        return StoreUnreachable(
            f"{url}: the S3 store at {endpoint} refused the request ({detail}); check the credentials "
            "AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY (and that AWS_ENDPOINT_URL is the right store)"
        )
    if kind == NO_BUCKET:
        return StoreUnreachable(
            f"{url}: the bucket {bucket!r} does not exist at {endpoint}; create it (e.g. `aws s3 mb s3://{bucket}`) "
            "or check the URL and AWS_ENDPOINT_URL"
        )
    return StoreUnreachable(
        f"{url}: cannot use the dataset store ({detail}); check the bucket, AWS_ENDPOINT_URL and the credentials "
        "(AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY)"
    )


def bucket_of(url: str) -> str:
    return url.split("://", 1)[1].split("/", 1)[0]


@contextlib.contextmanager
def store_errors(url: str) -> Iterator[None]:
    """Turn a failure of the store inside the block into one `StoreUnreachable` line; other errors
    (damage is already a `StorageError`, bugs keep their traceback) pass through."""
    try:
        yield
    except StorageError:
        raise
    except Exception as error:
        if is_store_failure(error):
            raise storage_failure(url, error) from None
        raise


def check_store(location: Location) -> None:
    """For ``s3://``: one HEAD of the bucket, with a short timeout and one retry, so a wrong
    endpoint, refused credentials or a missing bucket is one `StorageError` line within seconds,
    before anything is read or written. Other locations: nothing to check."""
    if not is_s3(location.url):
        return
    try:
        _probe_client(location.storage_options).head_bucket(Bucket=bucket_of(location.url))
    except Exception as error:
        if is_store_failure(error):
            raise storage_failure(location.url, error) from None
        raise


def _probe_client(options: dict[str, Any]) -> Any:
    """A plain botocore client with the location's endpoint, region and credentials (fsspec option
    names), its timeouts capped at `PROBE_TIMEOUT` and `PROBE_ATTEMPTS` attempts."""
    import botocore.config
    import botocore.session

    config_kwargs = dict(options.get("config_kwargs") or {})
    timeout = min(float(config_kwargs.get("connect_timeout", PROBE_TIMEOUT)), PROBE_TIMEOUT)
    read_timeout = min(float(config_kwargs.get("read_timeout", PROBE_TIMEOUT)), PROBE_TIMEOUT)
    config = botocore.config.Config(
        connect_timeout=timeout,
        read_timeout=read_timeout,
        retries={"max_attempts": PROBE_ATTEMPTS, "mode": "standard"},
    )
    client_kwargs = dict(options.get("client_kwargs") or {})
    arguments: dict[str, Any] = {
        "endpoint_url": options.get("endpoint_url") or client_kwargs.get("endpoint_url"),
        "region_name": client_kwargs.get("region_name"),
        "config": config,
    }
    if options.get("key"):
        arguments.update(aws_access_key_id=options["key"], aws_secret_access_key=options.get("secret"))
        arguments["aws_session_token"] = options.get("token")
    return botocore.session.get_session().create_client("s3", **arguments)
