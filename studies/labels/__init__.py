"""What the labels are and what they cost: search, ambiguity, refiners' effect (see README.md)."""
