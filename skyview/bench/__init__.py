"""Measurement: Monte Carlo benches of the methods (`runner`, on Dask with `dask_engine`), speed against the
peers (`speed`), centroid accuracy (`centroids`), sequences (`sequence`), method comparison (`compare`) and
sky coverage sweeps (`coverage`, `coverage_map`)."""
