"""What a trained planner achieves against the labels, fixed views and random ones (see README.md)."""
