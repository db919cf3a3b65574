"""What a dataset holds and whether it is right: listings, statistics, pictures, label checks and
relabelling, on top of `storage` (the `datagen shards` commands are thin wrappers over these)."""
