"""compabs pipelines: the method as pure functions over numpy arrays and BDDs (no Dask, Zarr or FastAPI)."""

from __future__ import annotations


def load_controller(directory, name: str = "controller"):
    """Load a controller saved by ``compabs run`` (see :func:`pipelines.controller.load_controller`)."""
    from pipelines.controller import load_controller as _load

    return _load(directory, name)


__all__ = ["load_controller"]
