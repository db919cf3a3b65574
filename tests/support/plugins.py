"""Installing and hiding plug-ins in a test: every registry (`schemas.registry.KINDS`) reads the
installed entry points once a process, so a test that changes what is installed makes them read
again (`forget_plugins`); the ``no_plugins`` fixture (tests/conftest.py) hides them all."""

from __future__ import annotations

from pathlib import Path

from schemas import registry


def forget_plugins() -> None:
    """Make every registry read the installed entry points again at its next use."""
    for kind in registry.KINDS:
        kind.forget_plugins()


def install_distribution(site: Path, dist: str, module: str, source: str, group: str, entry: str, value: str) -> None:
    """A distribution laid out as pip lays it out in ``site`` (a folder on sys.path or PYTHONPATH):
    ``module.py`` and a ``.dist-info`` whose entry point ``entry`` of ``group`` is ``value``."""
    (site / f"{module}.py").write_text(source)
    info = site / f"{dist}-0.1.dist-info"
    info.mkdir(exist_ok=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[{group}]\n{entry} = {value}\n")
    forget_plugins()
