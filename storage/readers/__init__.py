"""Reading samples: `open_dataset` (random access, ``ds[i]``, selections, splits) and `load_memory`
(a dataset's samples held in memory, batched without a reader), both through the one assembler of
`storage.samples`; `dataset_digest`, the content digest two runs of one job share.
The PyTorch readers are `storage.torch` (`OSVPDataset`) and `storage.stream` (`ShardStream`):
importing them imports torch, importing this does not.
"""

from typing import TYPE_CHECKING

from schemas.lazy import lazy_names

if TYPE_CHECKING:
    from storage.readers.digest import Digest, dataset_digest
    from storage.readers.memory import MemoryDataset, PackedCovers, load_index_facts, load_memory
    from storage.readers.reader import Dataset, LabelAmbiguity, NextView, Sample, mask_to_bools, open_dataset

__all__ = [
    "Dataset",
    "Digest",
    "LabelAmbiguity",
    "MemoryDataset",
    "NextView",
    "PackedCovers",
    "Sample",
    "dataset_digest",
    "load_index_facts",
    "load_memory",
    "mask_to_bools",
    "open_dataset",
]

_HOMES = {
    "Digest": "storage.readers.digest",
    "dataset_digest": "storage.readers.digest",
    "Dataset": "storage.readers.reader",
    "LabelAmbiguity": "storage.readers.reader",
    "NextView": "storage.readers.reader",
    "Sample": "storage.readers.reader",
    "mask_to_bools": "storage.readers.reader",
    "open_dataset": "storage.readers.reader",
    "MemoryDataset": "storage.readers.memory",
    "PackedCovers": "storage.readers.memory",
    "load_index_facts": "storage.readers.memory",
    "load_memory": "storage.readers.memory",
}
"""Where each public name is defined: imported from there when first used (`schemas.lazy`)."""
__getattr__, __dir__ = lazy_names(__name__, _HOMES)
