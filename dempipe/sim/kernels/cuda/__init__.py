"""The CUDA target: numba-cuda kernels of the stages (device, grid, contacts, bodies, backend)."""
