"""Many flights and settings at once: a sweep engine on Dask and the batch replay built on it."""
