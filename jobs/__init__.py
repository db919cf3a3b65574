"""The durable job queue: a SQLite ledger of jobs and tasks; no knowledge of meshes or Ray."""

from jobs.ledger import (
    CANCELLED,
    DONE,
    FAILED,
    FINAL_STATES,
    PENDING,
    RUNNING,
    Claim,
    Driver,
    Holders,
    Job,
    Ledger,
    LedgerError,
    LostDriver,
    Task,
)
from jobs.liveness import ProcessIdentity, process_alive, process_identity

__all__ = [
    "CANCELLED",
    "DONE",
    "FAILED",
    "FINAL_STATES",
    "PENDING",
    "RUNNING",
    "Claim",
    "Driver",
    "Holders",
    "Job",
    "Ledger",
    "LedgerError",
    "LostDriver",
    "ProcessIdentity",
    "Task",
    "process_alive",
    "process_identity",
]
