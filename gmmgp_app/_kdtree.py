"""The k-d tree of a scan's points, in a module light enough to import on ``gmmgp run``'s
reading thread (which builds it while the compute modules import): scipy's ``cKDTree``
with the sliding-midpoint rule (``balanced_tree=False``: built ~2x faster than the
median rule, the same query answers). :func:`gmmgp_app.pipeline.scan_tree` decides
which scans get one."""

from __future__ import annotations

import numpy as np

__all__ = ["points_tree"]


def points_tree(points: np.ndarray):
    """``cKDTree(points, balanced_tree=False)``."""
    from scipy.spatial import cKDTree

    return cKDTree(points, balanced_tree=False)
