"""How fast a dataset is read and inspected, and what a trainer installs (see README.md)."""
