"""Plain JSON values from results holding numpy scalars and arrays."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["jsonable"]


def jsonable(obj, nan_as_null: bool = False):
    """``obj`` with numpy scalars and arrays turned into Python numbers and lists (dict
    keys into strings); with ``nan_as_null`` non-finite floats become None (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v, nan_as_null) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, nan_as_null) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist(), nan_as_null) if nan_as_null else obj.tolist()
    if isinstance(obj, np.generic):
        obj = obj.item()
    if nan_as_null and isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
