"""language layer (see docs/architecture.md)."""
