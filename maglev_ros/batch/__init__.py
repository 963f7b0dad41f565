"""``maglev-ros batch``: a verb over an archive of recordings on Dask (jobs, manifest, engine,
summary; docs/batch.md)."""
