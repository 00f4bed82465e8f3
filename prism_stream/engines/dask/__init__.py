"""The Dask engine: the core's steps on a dask.distributed cluster (see :mod:`.driver`)."""

from .cluster import ClusterError, connect
from .driver import on_cluster, read_dataset, sample, sample_at

__all__ = ["ClusterError", "connect", "on_cluster", "read_dataset", "sample", "sample_at"]
