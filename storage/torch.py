"""PyTorch access, the documented path: `OSVPDataset` (fixed-size point clouds, view state, label, every
registered field) and `ShardShuffleSampler`, with `collate_samples`, the loader's collation.

Importing `storage` never imports torch; importing this module does. The readers themselves live in
`storage.readers` with the numpy ones; this module is their public face for PyTorch.
"""

from storage.readers.torch import OSVPDataset, ShardShuffleSampler, collate_samples

__all__ = ["OSVPDataset", "ShardShuffleSampler", "collate_samples"]
