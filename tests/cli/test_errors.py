"""One error root, one handler: every error a user can cause derives from `schemas.errors.DatagenError`,
and `datagen.cli.common.user_errors` prints each as one ``error:`` line on stderr with exit code 2."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from datagen.cli.common import EXIT_USER_ERROR, user_errors
from schemas.errors import DatagenError

ROOT = Path(__file__).resolve().parents[2]

ENUMERATE = textwrap.dedent(
    """
    import importlib, inspect, json, pkgutil

    from schemas.errors import DatagenError

    user, internal, skipped = [], [], []
    for root in ("schemas", "storage", "jobs", "datagen"):
        package = importlib.import_module(root)
        for info in pkgutil.walk_packages(package.__path__, root + "."):
            try:
                module = importlib.import_module(info.name)
            except ImportError as exc:  # an optional dependency that is not installed
                skipped.append(f"{info.name}: {exc}")
                continue
            for value in vars(module).values():
                if inspect.isclass(value) and issubclass(value, BaseException) and value.__module__ == info.name:
                    kind = user if issubclass(value, DatagenError) else internal
                    kind.append([info.name, value.__qualname__])
    print(json.dumps({"user": user, "internal": internal, "skipped": skipped}))
    """
)

INTERNAL = {
    ("datagen.shapes.families", "ShapeError"): "synthesize() catches it and draws new parameters; built-ins are fixed",
    ("datagen.inspection.label_check", "SolverFailure"): "becomes a problem line of `shards validate`",
    ("datagen.pipeline.setcover", "_BudgetExceeded"): "the solver's own control flow",
    ("datagen.pipeline.objects.ply_strips", "PlyError"): "load_mesh turns it into an ObjectError naming the file",
}
"""Exception classes that are not `DatagenError`s, and why no user ever sees them."""

EXPECTED = {
    ("storage.store.location", "StorageError"),
    ("jobs.ledger", "LedgerError"),
    ("datagen.errors", "ConfigError"),
    ("datagen.errors", "ObjectsFileError"),
    ("datagen.errors", "ObjectError"),
    ("datagen.errors", "ViewSpaceError"),
    ("datagen.errors", "InvalidArgument"),
    ("datagen.errors", "OutputError"),
    ("datagen.pipeline.setcover", "LabelError"),
}
"""Known user errors (more may be added; none may go missing)."""


@pytest.fixture(scope="module")
def exception_classes() -> dict[str, Any]:
    """Every exception class defined in schemas, storage, jobs and datagen, found by importing every
    module in a fresh interpreter (so this test process does not load Ray, torch or Open3D for it)."""
    done = subprocess.run(
        [sys.executable, "-c", ENUMERATE], cwd=ROOT, capture_output=True, text=True, timeout=300, check=False
    )
    assert done.returncode == 0, done.stderr
    found: dict[str, Any] = json.loads(done.stdout.splitlines()[-1])
    return found


def test_every_user_facing_error_derives_from_the_one_root(exception_classes: dict[str, Any]) -> None:
    user = {tuple(pair) for pair in exception_classes["user"]}
    internal = {tuple(pair) for pair in exception_classes["internal"]}
    assert not EXPECTED - user, (EXPECTED - user, exception_classes["skipped"])
    unexplained = internal - set(INTERNAL)
    assert not unexplained, f"derive these from DatagenError, or say in INTERNAL why no user sees them: {unexplained}"


def test_the_root_lives_in_schemas_and_every_layer_shares_it() -> None:
    import datagen.errors
    import jobs
    import schemas
    import storage

    assert schemas.DatagenError is datagen.errors.DatagenError is DatagenError
    assert issubclass(storage.StorageError, DatagenError)
    assert issubclass(jobs.LedgerError, DatagenError)
    assert DatagenError.__module__ == "schemas.errors"


def _app_raising(error: BaseException) -> typer.Typer:
    app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)

    @app.command()
    def fail() -> None:
        with user_errors():
            raise error

    return app


# Brackets that rich would read as markup, and a line longer than any terminal: printed verbatim, unwrapped.
MESSAGE = "[bold]/tmp/x[/bold]: " + "a long message that must stay on one line, " * 8 + "do this to fix it"


def test_the_one_handler_prints_every_user_error_as_one_line(exception_classes: dict[str, Any]) -> None:
    assert exception_classes["user"]
    for module_name, qualname in exception_classes["user"]:
        error_type = getattr(importlib.import_module(module_name), qualname)
        result = CliRunner().invoke(_app_raising(error_type(MESSAGE)), [])
        assert result.exit_code == EXIT_USER_ERROR == 2, (qualname, result.output)
        assert result.exception is None or isinstance(result.exception, SystemExit), (qualname, result.exception)
        assert result.stderr == f"error: {MESSAGE}\n", qualname
        assert result.stdout == "", qualname


def test_a_bug_keeps_its_traceback() -> None:
    result = CliRunner().invoke(_app_raising(RuntimeError("a bug")), [])
    assert isinstance(result.exception, RuntimeError)
    assert "error:" not in result.stderr
