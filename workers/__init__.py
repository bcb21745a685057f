"""Running the method on Dask (ARCHITECTURE: ``service -> workers -> pipelines``).

Modules, one responsibility each:

- :mod:`workers.cluster`: ``connect()`` to an embedded LocalCluster or an external scheduler.
- :mod:`workers.store`: the Zarr v3 relation store (``DIR/relations.zarr``), chunk writes and done-markers.
- :mod:`workers.tasks`: ``abstract_chunk``, the task the cluster runs (importable by scheduler and workers).
- :mod:`workers.runner`: ``run_job()``, the stages of ``workers.job`` with chunks on the cluster, resumable.
- :mod:`workers.errors`: the runner's errors (all ``CompabsError``).

Nothing is imported here, so ``import workers`` does not import Dask or Zarr.
"""
