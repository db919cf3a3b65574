"""Reading and writing datasets on any fsspec URL (Zarr v3 shards, Parquet index).

The storage layer lands with the storage issue; the package exists now so that the distribution's
layout (``schemas <- storage <- datagen -> jobs``) is fixed from the first commit.
"""
