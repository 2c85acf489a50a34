"""Experiments: sweeps of training runs on Dask and their tables (docs/method.md §10)."""
