"""Stages chained: one subject's chain, batches on Dask distributed, error-against-time
reports."""
