"""Many bakes at once on Dask: wedges of a scene over seeds and keys, on a workstation or a farm."""
