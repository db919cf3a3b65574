"""Pure per-task steps of PIPELINE.md, in its order: numpy in, numpy out; no Ray, storage or ledger."""
