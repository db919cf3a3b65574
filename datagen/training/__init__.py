"""Training and measuring the POCO refiner's weights (never loaded by a worker that only refines).

- `poco_samples`: training examples cut from scans of the project's own shapes; the sample pool.
- `poco_train`: batches and the resumable training loop (``datagen poco train``).
- `poco_validation`: a model's metrics on pool samples and the decision threshold it implies.
- `poco_checkpoints`: the run folder's checkpoints and the exported weights file (``datagen poco export``).
- `poco_eval`: refiners against true occupancy on whole objects (``datagen poco eval``).

What the network sees is shared with the refiner: `datagen.pipeline.refine.poco.inputs`.
"""
