"""Scenes: TOML files and UsdPhysics stages read into a Scene, and the Model built from it."""
