"""The durable job queue: a SQLite ledger of jobs and tasks; no knowledge of meshes or Ray."""

from jobs.ledger import (
    CANCELLED,
    DONE,
    FAILED,
    FINAL_STATES,
    PENDING,
    RUNNING,
    Claim,
    Job,
    Ledger,
    LedgerError,
    Task,
)

__all__ = [
    "CANCELLED",
    "DONE",
    "FAILED",
    "FINAL_STATES",
    "PENDING",
    "RUNNING",
    "Claim",
    "Job",
    "Ledger",
    "LedgerError",
    "Task",
]
