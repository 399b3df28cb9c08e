"""Robustness campaigns: many runs of one compiled closed loop over a scenario's `[[uncertainty]]`, locally or on a
dask cluster, into results.parquet, summary.json and worst.toml."""
