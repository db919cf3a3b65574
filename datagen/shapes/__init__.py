"""Built-in and seeded synthetic shapes: meshes made here, not read from users."""
