"""The slab driver: grids and their plans, memory budgets, executors (this process, worker
processes, a Dask cluster), and the exact reductions across slabs (level quantiles, components)."""
