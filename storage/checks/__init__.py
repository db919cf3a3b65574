"""Checking and mending a dataset: `validate` (structure, every file, and that every label covers
its U; numpy only), the file-level checks it runs (``file_checks``), and `withdraw`, the storage half
of ``datagen shards repair``. It reads shards and records itself: it imports `storage.store`,
`storage.samples`, `storage.shards` and `storage.dataset`, not the readers.
"""

from typing import TYPE_CHECKING

from schemas.lazy import lazy_names

if TYPE_CHECKING:
    from storage.checks.repair import Findings, sort_problems, withdraw
    from storage.checks.validation import (
        SAMPLED_ROWS_PER_SHARD,
        Validation,
        ValidationPlan,
        check_dataset,
        check_tasks,
        plan_validation,
        validate,
        validate_dataset,
    )

__all__ = [
    "SAMPLED_ROWS_PER_SHARD",
    "Findings",
    "Validation",
    "ValidationPlan",
    "check_dataset",
    "check_tasks",
    "plan_validation",
    "sort_problems",
    "validate",
    "validate_dataset",
    "withdraw",
]

_HOMES = {
    "SAMPLED_ROWS_PER_SHARD": "storage.checks.validation",
    "Validation": "storage.checks.validation",
    "ValidationPlan": "storage.checks.validation",
    "check_dataset": "storage.checks.validation",
    "check_tasks": "storage.checks.validation",
    "plan_validation": "storage.checks.validation",
    "validate": "storage.checks.validation",
    "validate_dataset": "storage.checks.validation",
    "Findings": "storage.checks.repair",
    "sort_problems": "storage.checks.repair",
    "withdraw": "storage.checks.repair",
}
"""Where each public name is defined: imported from there when first used (`schemas.lazy`)."""
__getattr__, __dir__ = lazy_names(__name__, _HOMES)
