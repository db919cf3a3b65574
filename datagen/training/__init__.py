"""Training and measuring the POCO refiner's weights (never loaded by a worker that only refines)."""
