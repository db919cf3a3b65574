"""Users' objects: objects files, what each line names, and preparation into the object frame."""
