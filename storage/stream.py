"""Streaming reads for PyTorch, the documented path: `ShardStream`, an ``IterableDataset`` that reads
whole shards in DataLoader workers and batches their samples through storage's one assembler.

Importing `storage` never imports torch; importing this module does. The reader itself lives in
`storage.readers` with the others; this module is its public face for PyTorch.
"""

from storage.readers.stream import ShardStream

__all__ = ["ShardStream"]
