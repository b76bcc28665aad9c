"""Many independent runs at once: worker processes, vmapped sweeps, Dask clusters."""
