"""``osvp``: the AIR-OSVP one-shot view planner, trained on datagen shards.

It reads datasets only through `storage` (and its `schemas`), with torch and numpy: never
`datagen`, Ray, Embree, trimesh or HiGHS, so training runs wherever the shards can be read.
`osvp.planning.load_scorer` is what `datagen evaluate --planner osvp:FILE` calls.
"""

__version__ = "0.1.0"
