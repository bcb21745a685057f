"""Running the method (ARCHITECTURE: ``service -> workers -> pipelines``).

- :mod:`workers.job`: the one orchestrator: the stages of a job, defined once (``run_job``, ``abstract_job``,
  ``run_abstraction``); :mod:`workers.control`: its synthesis, closed-loop and figure stages;
  :mod:`workers.job_session`: what a job holds open between them (its Dask client, cluster, audit beside synthesis).
- :mod:`workers.executors`: where the per-cell tasks run: in this process or on Dask (``InProcess``, ``OnDask``).
- :mod:`workers.cluster`: ``connect()`` to an embedded LocalCluster or an external scheduler.
- :mod:`workers.tasks`: ``abstract_chunk``, the task the cluster runs (importable by scheduler and workers).
- :mod:`workers.relation_store`: the Zarr v3 relation store (``DIR/relations.zarr``), chunk writes and done-markers.
- :mod:`workers.jobdir`: the job directory: every path, reader and writer.
- :mod:`workers.job_audit`: ``audit_job``, the audit of a finished job's stored files (``compabs audit``).
- :mod:`workers.processes`: local helper processes: the audit beside synthesis, the partitioned CPre.
- :mod:`workers.errors`: the execution errors (all ``CompabsError``).

Nothing is imported here, so ``import workers`` does not import Dask or Zarr.
"""
