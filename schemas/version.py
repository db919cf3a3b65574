"""Version of the on-disk dataset layout; bumped on any change a reader must know about."""

SCHEMA_VERSION = 1
