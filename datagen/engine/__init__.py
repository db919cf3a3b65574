"""Running jobs: the Ray driver, the Ray-free worker, shard payloads, job planning, relabel, serve."""
