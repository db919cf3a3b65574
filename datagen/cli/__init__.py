"""The ``datagen`` command line (typer)."""
