"""`datagen.cli` has no import cycle: command modules import only `datagen.cli.common` from their
package, the registrars (`main`, and `shards` for its group) import the command modules, and every
module imports first, in a fresh interpreter, without error."""

from __future__ import annotations

import ast
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import datagen.cli

ROOT = Path(__file__).resolve().parents[2]
CLI = Path(datagen.cli.__file__).parent
MODULES = sorted(f"datagen.cli.{info.name}" for info in pkgutil.iter_modules(datagen.cli.__path__))
REGISTRARS = {"datagen.cli.main", "datagen.cli.shards"}


def cli_imports(module: str) -> set[str]:
    """The `datagen.cli` modules a module imports (at any depth of its code)."""
    tree = ast.parse((CLI / f"{module.rsplit('.', 1)[1]}.py").read_text())
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.module == "datagen.cli":
                found.update(f"datagen.cli.{alias.name}" for alias in node.names)
            elif node.module.startswith("datagen.cli."):
                found.add(node.module)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.startswith("datagen.cli."))
    return found


def test_the_expected_modules_are_there() -> None:
    assert {"datagen.cli.common", "datagen.cli.main", "datagen.cli.shards", "datagen.cli.poco"} <= set(MODULES)


@pytest.mark.parametrize("module", [m for m in MODULES if m not in REGISTRARS])
def test_command_modules_import_only_common(module: str) -> None:
    assert cli_imports(module) <= {"datagen.cli.common"}, module


def test_registrars_import_no_registrar_back() -> None:
    assert "datagen.cli.main" not in cli_imports("datagen.cli.shards")
    for module in MODULES:
        if module != "datagen.cli.main":
            assert "datagen.cli.main" not in cli_imports(module), module


@pytest.mark.parametrize("first", MODULES)
def test_each_module_imports_first_in_a_fresh_interpreter(first: str) -> None:
    """A cycle shows as an ImportError that depends on which module of it is imported first."""
    others = [m for m in MODULES if m != first]
    code = "import importlib\n" + "".join(f"importlib.import_module({name!r})\n" for name in [first, *others])
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
