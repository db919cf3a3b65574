"""The simulated one-shot run: what a planner's views achieve on real objects (coverage, views, movement)."""
