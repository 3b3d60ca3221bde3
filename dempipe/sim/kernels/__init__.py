"""The eight stages as kernels: what both targets share here, the drivers in cpu/ and cuda/."""
