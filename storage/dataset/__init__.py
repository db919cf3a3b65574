"""A dataset as files: the commit protocol, its manifest and index, ``dataset.json``, and packing.

``writer`` commits a task (shard, index fragment, then its commit record, last and atomically) and
records failures; ``manifest`` is what a reader opens instead of one record and fragment per task;
``index`` finalises and opens the index (``sample_index``: where each sample lives); ``info`` creates
and reads ``dataset.json``; ``pack`` packs a finished dataset into a few large tar files; ``problems``
are the records of what is damaged and what mends it. It imports `storage.store` and `storage.shards`.
"""

from typing import TYPE_CHECKING

from schemas.lazy import lazy_names

if TYPE_CHECKING:
    from storage.dataset.index import (
        INDEX_COVERAGE_FILE,
        INDEX_FILE,
        finalise,
        index_rows_of,
        load_index,
        merge_fragments,
        open_index,
    )
    from storage.dataset.info import existing_info, init_dataset, read_info
    from storage.dataset.manifest import (
        ADDING_FILE,
        MANIFEST_FILE,
        Manifest,
        mark_adding,
        read_manifest,
        read_tasks,
        record_of,
        task_records,
    )
    from storage.dataset.pack import PackProgress, PackSummary, pack_dataset
    from storage.dataset.problems import Mend, Problem, lines
    from storage.dataset.sample_index import SampleIndex
    from storage.dataset.writer import (
        COMMITS,
        FAILURES,
        SHARDS,
        ShardPayload,
        commit_path,
        committed_tasks,
        failure_path,
        fragment_path,
        holds_dataset,
        line_failure_id,
        read_commit,
        read_commits,
        read_failures,
        retire_line_failures,
        shard_path,
        stored_bytes,
        sweep_orphans,
        sweep_temporaries,
        write_failure,
        write_task,
    )

__all__ = [
    "ADDING_FILE",
    "COMMITS",
    "FAILURES",
    "INDEX_COVERAGE_FILE",
    "INDEX_FILE",
    "MANIFEST_FILE",
    "SHARDS",
    "Manifest",
    "Mend",
    "PackProgress",
    "PackSummary",
    "Problem",
    "SampleIndex",
    "ShardPayload",
    "commit_path",
    "committed_tasks",
    "existing_info",
    "failure_path",
    "finalise",
    "fragment_path",
    "holds_dataset",
    "index_rows_of",
    "init_dataset",
    "line_failure_id",
    "lines",
    "load_index",
    "mark_adding",
    "merge_fragments",
    "open_index",
    "pack_dataset",
    "read_commit",
    "read_commits",
    "read_failures",
    "read_info",
    "read_manifest",
    "read_tasks",
    "record_of",
    "retire_line_failures",
    "shard_path",
    "stored_bytes",
    "sweep_orphans",
    "sweep_temporaries",
    "task_records",
    "write_failure",
    "write_task",
]

_HOMES = {
    "Mend": "storage.dataset.problems",
    "Problem": "storage.dataset.problems",
    "lines": "storage.dataset.problems",
    "COMMITS": "storage.dataset.writer",
    "FAILURES": "storage.dataset.writer",
    "SHARDS": "storage.dataset.writer",
    "ShardPayload": "storage.dataset.writer",
    "commit_path": "storage.dataset.writer",
    "committed_tasks": "storage.dataset.writer",
    "failure_path": "storage.dataset.writer",
    "fragment_path": "storage.dataset.writer",
    "holds_dataset": "storage.dataset.writer",
    "line_failure_id": "storage.dataset.writer",
    "read_commit": "storage.dataset.writer",
    "read_commits": "storage.dataset.writer",
    "read_failures": "storage.dataset.writer",
    "retire_line_failures": "storage.dataset.writer",
    "shard_path": "storage.dataset.writer",
    "stored_bytes": "storage.dataset.writer",
    "sweep_orphans": "storage.dataset.writer",
    "sweep_temporaries": "storage.dataset.writer",
    "write_failure": "storage.dataset.writer",
    "write_task": "storage.dataset.writer",
    "ADDING_FILE": "storage.dataset.manifest",
    "MANIFEST_FILE": "storage.dataset.manifest",
    "Manifest": "storage.dataset.manifest",
    "mark_adding": "storage.dataset.manifest",
    "read_manifest": "storage.dataset.manifest",
    "read_tasks": "storage.dataset.manifest",
    "record_of": "storage.dataset.manifest",
    "task_records": "storage.dataset.manifest",
    "existing_info": "storage.dataset.info",
    "init_dataset": "storage.dataset.info",
    "read_info": "storage.dataset.info",
    "INDEX_COVERAGE_FILE": "storage.dataset.index",
    "INDEX_FILE": "storage.dataset.index",
    "finalise": "storage.dataset.index",
    "index_rows_of": "storage.dataset.index",
    "load_index": "storage.dataset.index",
    "merge_fragments": "storage.dataset.index",
    "open_index": "storage.dataset.index",
    "SampleIndex": "storage.dataset.sample_index",
    "PackProgress": "storage.dataset.pack",
    "PackSummary": "storage.dataset.pack",
    "pack_dataset": "storage.dataset.pack",
}
"""Where each public name is defined: imported from there when first used (`schemas.lazy`)."""
__getattr__, __dir__ = lazy_names(__name__, _HOMES)
