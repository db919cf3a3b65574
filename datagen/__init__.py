"""datagen: exact, reproducible training data for one-shot view planning.

The pipeline modules are plain functions on numpy arrays (``design/PIPELINE.md``); the engine and
the CLI compose them.
"""

__version__ = "0.1.0"
