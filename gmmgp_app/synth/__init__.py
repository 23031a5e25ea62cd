"""Synthetic scenes with exact ground truth and a simulated LiDAR scanner.

>>> from gmmgp_app.synth import make_scene, scan_scene
>>> scene = make_scene("street")                     # watertight mesh + exact SDF
>>> d = scene.sdf([[10.0, 0.0, 1.0]])                # metres, free space positive
>>> scan, scene = scan_scene("street", density=0.05)  # doctest: +SKIP

See :mod:`.scenes` for the scenes, :mod:`.meshsdf` for the exact signed distance
and :mod:`.scanner` for the mobile-mapping and terrestrial scanner models.
"""

from .meshsdf import MeshDistance, MeshError, edge_topology, mesh_signed_distance
from .scenes import (LABELS, SCENES, SynthError, SyntheticScene, box_sdf, make_scene,
                     mesh_topology, sphere_sdf)

__all__ = [
    "LABELS", "SCENES", "SynthError", "SyntheticScene", "make_scene", "box_sdf", "sphere_sdf",
    "mesh_topology", "MeshDistance", "MeshError", "edge_topology", "mesh_signed_distance",
]

from .scanner import cast_rays, scan_scene, simulate_mms, simulate_static  # noqa: E402

__all__ += ["cast_rays", "scan_scene", "simulate_mms", "simulate_static"]

from .io import save_mesh_ply, save_scan_npz, write_scene  # noqa: E402

__all__ += ["save_mesh_ply", "save_scan_npz", "write_scene"]
