"""gmmgp_app: uncertain implicit surface mapping from LiDAR scans with a
hierarchical GMM prior and local Gaussian processes.

>>> import gmmgp_app as gm
>>> cfg = gm.MappingConfig()
>>> scan = gm.read_scan("scan.ply")                      # doctest: +SKIP
>>> smap = gm.build_map(scan, cfg)                        # doctest: +SKIP
>>> mean, var = smap.predict(xyz)                         # doctest: +SKIP

Public names are imported lazily so that ``gmmgp --help`` stays fast.
"""

import os
from importlib import import_module

# numba's TBB layer refuses the TBB that Open3D's wheels bring (too old) and warns on
# every parallel kernel; OpenMP is what it would fall back to anyway.
os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

__version__ = "0.1.0"

_PUBLIC = {
    "MappingConfig": "gmmgp_app.config",
    "ConfigError": "gmmgp_app.config",
    "Scan": "gmmgp_app.types",
    "TrainingSet": "gmmgp_app.types",
    "GaussianMixture": "gmmgp_app.types",
    "HGMMLevel": "gmmgp_app.types",
    "HierarchicalGMM": "gmmgp_app.types",
    "SurfaceMesh": "gmmgp_app.types",
    "read_scan": "gmmgp_app.datasets",
    "ScanReadError": "gmmgp_app.datasets",
    "ScanWarning": "gmmgp_app.datasets",
    "scan_summary": "gmmgp_app.datasets",
    "prepare": "gmmgp_app.pipeline",
    "fit_hgmm": "gmmgp_app.pipeline",
    "build_map": "gmmgp_app.pipeline",
    "SurfaceMap": "gmmgp_app.pipeline",
    "load_map": "gmmgp_app.pipeline",
    "check_scan": "gmmgp_app.check",
    "CheckResult": "gmmgp_app.check",
}

__all__ = sorted(_PUBLIC) + ["__version__"]


def __getattr__(name):
    if name in _PUBLIC:
        value = getattr(import_module(_PUBLIC[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'gmmgp_app' has no attribute {name!r}")


def __dir__():
    return __all__
