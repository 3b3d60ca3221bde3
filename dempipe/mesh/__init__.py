"""Meshes: the built-in shapes, mesh files loaded and repaired, inside tests by winding number."""
