"""Executors: where the core's steps run (this machine, a DuckDB query's result, a Dask cluster)."""
