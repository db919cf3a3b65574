"""The ``datagen`` command line (typer).

`main` builds the apps and registers plain functions from the command modules `inputs` (config,
objects, scan), `jobs` (submit, status, cancel, resume, serve), the `shards` group (`shards_view`,
`shards_check`, `shards_export`) and the `poco` group (`poco`). Command modules import only
`common` from this package: the consoles and `user_errors`, the one handler that prints any
`DatagenError` as one ``error:`` line and exits 2.
"""
