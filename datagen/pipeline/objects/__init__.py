"""Objects: objects files, built-in and synthetic shapes, and preparation into the object frame."""
