"""Benchmarks of datagen, by question: generation, labels, reading, planners (see README.md)."""
