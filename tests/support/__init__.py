"""Helpers shared by the tests (and a few benchmarks): fixtures, oracles, references."""
