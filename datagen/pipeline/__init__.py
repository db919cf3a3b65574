"""Pure per-task steps of docs/pipeline.md, in its order: numpy in, numpy out; no Ray, storage or ledger."""
