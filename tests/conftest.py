"""Shared fixtures. The real data lives beside the project, in ../shared/data."""

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ../shared/data (see its DATA.md); skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real scan data not found at {SHARED_DATA} (../shared/data is absent)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def load_script():
    """``load(name) -> module``: ``scripts/<name>.py`` imported under its own module name
    (``<name>_under_test``), for tests of a script's functions."""
    import importlib.util

    def load(name: str):
        spec = importlib.util.spec_from_file_location(
            f"{name}_under_test", Path(__file__).resolve().parents[1] / "scripts" / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod
    return load


@pytest.fixture(scope="session")
def box_scene(tmp_path_factory):
    """A small scanned synthetic box (scan_scene("box", density=0.03)): a folder with
    its ``scan.npz`` and exact ``mesh.ply``, and the Scan. Tests write only below
    their own subfolders of it."""
    from gmmgp_app.synth import save_mesh_ply, save_scan_npz, scan_scene

    root = tmp_path_factory.mktemp("box")
    scan, scene = scan_scene("box", density=0.03)
    save_scan_npz(root / "scan.npz", scan.points, scan.origins)
    save_mesh_ply(root / "mesh.ply", scene)
    return root, scan


@pytest.fixture
def count_scan_trees(monkeypatch):
    """``count(points) -> list``: from then on every k-d tree built (by scipy, the scale
    measurement or the prepare stage) appends whether it was of ``points`` (the same
    array object) to the returned list."""
    import scipy.spatial

    from gmmgp_app.stages import autoscale, prepare

    def count(points):
        built = []
        real = scipy.spatial.cKDTree

        def counting(data, *a, **k):
            built.append(data is points)
            return real(data, *a, **k)

        for mod in (scipy.spatial, autoscale, prepare):
            monkeypatch.setattr(mod, "cKDTree", counting)
        return built

    return count
