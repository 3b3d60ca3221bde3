"""The CPU target: numba njit/prange drivers of the eight stages (device, grid, stages, backend)."""
