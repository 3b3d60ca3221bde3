"""Sphere sets: a body as equal spheres (lattice or surface), their fidelity, the disk cache."""
