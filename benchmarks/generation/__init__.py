"""How fast a dataset is made: imaging, cases, refinement, a task's steps, whole jobs (see README.md)."""
