"""A bake from file to file: bake() and analyze_scene(), with checkpoints, chunks and resume."""
