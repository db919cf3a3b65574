"""Version of the on-disk dataset layout; bumped on any change a reader must know about.

1: samples, labels and the per-task sets. 2 adds each label's ambiguity: every minimum cover (up to
the config's cap), their count and support, and the task's cover rows. 3 adds the next-best-view
labels (every view's gain, the best next view) and the occupancy grid's per-view ray cells. 4 stores
each sample's refined cloud in a seeded random order, in small chunks, so that a reader wanting N points
decodes only the chunks of one window of that order (`schemas.shard.point_order`). 5 keeps a task's
whole group in one file (an uncompressed ZIP of the same Zarr members: a handful of files a task
instead of about 40). Readers read every version; writers add tasks to a dataset in its own version.
"""

SCHEMA_VERSION = 5
READABLE_SCHEMA_VERSIONS = (1, 2, 3, 4, 5)


def unreadable_version(version: int) -> str | None:
    """Why this code cannot read layout ``version`` (a dataset of a newer datagen), None when it can."""
    if version in READABLE_SCHEMA_VERSIONS:
        return None
    known = ", ".join(str(v) for v in READABLE_SCHEMA_VERSIONS)
    return f"schema version {version}; this reader knows {known}: upgrade datagen"
