"""The durable job queue (a SQLite ledger of jobs and tasks); no knowledge of meshes or Ray.

The ledger lands with the engine issue; the package exists now so that the distribution's layout
(``schemas <- storage <- datagen -> jobs``) is fixed from the first commit.
"""
