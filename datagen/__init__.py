"""datagen: exact, reproducible training data for one-shot view planning.

The pipeline modules are plain functions on numpy arrays (``docs/pipeline.md``); the engine and
the CLI compose them.
"""

from typing import Any

__version__ = "0.1.0"


def submit(*args: Any, **kwargs: Any) -> Any:
    """Plan and run a job now: `datagen.api.submit` (imported on first use; it brings in Ray)."""
    from datagen.api import submit as _submit

    return _submit(*args, **kwargs)
