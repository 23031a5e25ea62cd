"""Writing a simulated scene to disk: ``scan.npz``, ``mesh.ply``, ``scene.json``.

Every file is written to a temporary name in the destination folder and then
moved into place with :func:`os.replace`, so a crash never leaves a
half-written output under the final name.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .._atomic import atomic_path
from .scanner import scan_scene
from .scenes import LABELS, SynthError, SyntheticScene

__all__ = ["write_scene", "save_scan_npz", "save_mesh_ply"]


def _atomic(path: Path, write, suffix: str) -> None:
    """Call ``write(tmp_path)`` and move the result onto ``path``."""
    with atomic_path(path, suffix) as tmp:
        write(str(tmp))


def save_scan_npz(path, points, origins=None, labels=None, *, dtype=np.float64) -> Path:
    """Write ``points`` (N,3), ``origins`` (N,3) and ``labels`` (N,) int64 to a compressed npz.

    ``dtype=np.float32`` halves the size (used for the bundled demo asset;
    readers convert back to float64).
    """
    path = Path(path)
    arrays = {"points": np.asarray(points, dtype=dtype)}
    if origins is not None:
        arrays["origins"] = np.asarray(origins, dtype=dtype)
    if labels is not None:
        arrays["labels"] = np.asarray(labels, dtype=np.int64)

    def write(tmp):
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)

    _atomic(path, write, ".npz")
    return path


def save_mesh_ply(path, scene: SyntheticScene) -> Path:
    """Write the ground-truth mesh of ``scene`` as a binary PLY through Open3D."""
    import open3d as o3d

    path = Path(path)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(scene.vertices),
                                     o3d.utility.Vector3iVector(scene.faces.astype(np.int32)))

    def write(tmp):
        if not o3d.io.write_triangle_mesh(tmp, mesh, write_ascii=False, compressed=False,
                                          write_vertex_normals=False,
                                          write_vertex_colors=False):
            raise OSError(f"Open3D could not write the mesh to '{tmp}'.")

    _atomic(path, write, ".ply")
    return path


def write_scene(name: str, out_dir, *, density: float = 1.0, seed: int = 0,
                scene_params=None, **scanner_kw) -> dict:
    """Simulate a scene and write ``scan.npz``, ``mesh.ply`` and ``scene.json`` to ``out_dir``.

    Parameters
    ----------
    name : str
        One of :data:`~gmmgp_app.synth.SCENES`.
    out_dir : path
        Created if missing.
    density, seed, scene_params, **scanner_kw
        As in :func:`~gmmgp_app.synth.scan_scene`.

    Returns
    -------
    dict
        ``{"scan": Path, "mesh": Path, "scene": Path}``.

    Raises
    ------
    SynthError
        Bad scene name or parameters, or ``out_dir`` is an existing file.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise SynthError(f"Expected an output folder, found the file '{out}'; "
                         "pass a folder path to --out.")
    scan, scene = scan_scene(name, density=density, seed=seed, scene_params=scene_params,
                             **scanner_kw)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"scan": save_scan_npz(out / "scan.npz", scan.points, scan.origins, scan.labels),
             "mesh": save_mesh_ply(out / "mesh.ply", scene)}
    counts = np.bincount(scan.labels, minlength=len(LABELS))
    meta = {
        "name": name,
        "seed": int(seed),
        "density": float(density),
        "scene_params": scene.params,
        "scanner": {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                    for k, v in scanner_kw.items()},
        "source": scan.source,
        "n_points": int(len(scan)),
        "n_vertices": int(len(scene.vertices)),
        "n_faces": int(len(scene.faces)),
        "bounds": scene.bounds.tolist(),
        "labels": {LABELS[i]: int(c) for i, c in enumerate(counts) if c},
        "label_ids": {str(k): v for k, v in LABELS.items()},
        "sdf_convention": "signed distance to mesh.ply, free space positive, metres",
    }

    def write(tmp):
        with open(tmp, "w") as fh:
            json.dump(meta, fh, indent=2)
            fh.write("\n")

    paths["scene"] = out / "scene.json"
    _atomic(paths["scene"], write, ".json")
    return paths
