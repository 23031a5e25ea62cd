"""gmmgp side by side with a TSDF peer (VDBFusion) on the same scans, in one run.

Cases: the synthetic street at full density (about 1.3M points, per-point sensor
origins, exact mesh), a random 10 % subset of it, and a KITTI Velodyne scan (sensor
at the origin of its own frame; the scan itself is the reference). Each mapper runs
as its own process, so its wall time and peak RSS (``ru_maxrss`` from ``wait4``) are
its own: ``gmmgp run SCAN --out DIR`` (read, map, mesh, save) and a small VDBFusion
runner (read, integrate, mesh, save).

VDBFusion (PyPI ``vdbfusion``; C++ on OpenVDB) publishes wheels only for older
Pythons, so the benchmark makes its own side environment in ``.peers/`` (gitignored)
from an older interpreter found on the machine (pyenv versions, python3.8-3.10 on the
PATH) and skips VDBFusion with one line when there is none. The project does not
depend on it. Its settings: 5 cm voxels, truncation 0.3 m, no space carving, no hole
filling, the points grouped by sensor position (origins pooled in 5 cm cells, each
group integrated from its mean origin).

Mesh metrics, computed afterwards in this process (not timed):
- accuracy: distance from area-weighted samples of the mesh to the exact mesh
  (KITTI: to the nearest scan point), mean, RMSE and 95th percentile;
- completeness: the observed exact surface (area-weighted samples of the exact mesh
  within 10 cm of the points the mapper was given; KITTI: the scan points) within
  1, 2 and 5 cm of the mesh, and the mean distance;
- chamfer: mean of the two mean distances.

    .venv/bin/python scripts/bench_peers.py                  # out/bench/bench_peers.{json,md}
    .venv/bin/python scripts/bench_peers.py --cases street10,kitti --repeats 3
    .venv/bin/python scripts/bench_peers.py --gmmgp-arg=--set --gmmgp-arg=gp.d_m=0.03
    .venv/bin/python scripts/bench_peers.py --repo /path/to/other/checkout   # map with its code
    .venv/bin/python scripts/bench_peers.py --keep-runs     # keep every run's map and mesh

The mapper runs the code of ``--repo`` (default: this script's own repository),
whatever PYTHONPATH or the current folder hold; the JSON names it (``mapper``: the
folder, its commit, whether it has uncommitted changes).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

VOXEL, TRUNC, ORIGIN_CELL = 0.05, 0.3, 0.05
KITTI = ROOT.parent / "shared" / "data" / "kitti_odometry_seq00" / "velodyne" / "000000.bin"
CASES = ("street", "street10", "kitti")

RUNNER = r'''
import sys, time, json
t0 = time.perf_counter()
import numpy as np
import vdbfusion
scan, out, voxel, trunc, cell = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])
z = np.load(scan)
pts, org = np.ascontiguousarray(z["points"], dtype=np.float64), z["origins"].astype(np.float64)
t1 = time.perf_counter()
key = np.floor(org / cell).astype(np.int64)
_, inv = np.unique(key, axis=0, return_inverse=True)
inv = inv.reshape(-1)
order = np.argsort(inv, kind="stable")
bounds = np.flatnonzero(np.diff(inv[order])) + 1
vol = vdbfusion.VDBVolume(voxel, trunc, False)
groups = np.split(order, bounds)
for g in groups:
    vol.integrate(np.ascontiguousarray(pts[g]), org[g].mean(0))
t2 = time.perf_counter()
v, f = vol.extract_triangle_mesh(False, 0.0)
t3 = time.perf_counter()
np.savez(out, vertices=np.asarray(v, dtype=np.float64), faces=np.asarray(f, dtype=np.int64))
json.dump({"seconds": {"read": t1 - t0, "integrate": t2 - t1, "mesh": t3 - t2,
                       "write": time.perf_counter() - t3},
           "groups": len(groups), "version": getattr(vdbfusion, "__version__", "?")},
          open(out + ".json", "w"))
'''


# --------------------------------------------------------------------------- processes
def mapper_command(repo, scan, out, extra=(), environ=None) -> tuple:
    """``(cmd, env, cwd)`` of one ``gmmgp run`` of the benchmark: ``gmmgp run SCAN --out
    OUT -q EXTRA`` importing gmmgp_app from ``repo``. The repository comes first on the
    child's PYTHONPATH and is its working folder (``python -m`` puts the working folder
    before PYTHONPATH: started from another checkout, the child imported that one), so
    neither the caller's PYTHONPATH nor its folder choose the mapper's code; the other
    PYTHONPATH entries follow. Paths are made absolute (the child starts in ``repo``)."""
    repo = Path(repo).resolve()
    environ = os.environ if environ is None else environ
    rest = [p for p in environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    env = dict(environ, PYTHONPATH=os.pathsep.join([str(repo), *rest]))
    cmd = [sys.executable, "-m", "gmmgp_app.cli", "run", str(Path(scan).resolve()),
           "--out", str(Path(out).resolve()), "-q", *map(str, extra)]
    return cmd, env, repo


def mapper_source(repo) -> dict:
    """What the JSON says of the mapper's code: its folder, git commit and whether the
    checkout has uncommitted changes to tracked files (None when not a git checkout)."""
    repo = Path(repo).resolve()

    def git(*a):
        r = subprocess.run(["git", "-C", str(repo), *a], capture_output=True, text=True)
        return r.stdout.strip() if r.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {"repo": str(repo), "commit": commit,
            "modified": None if status is None else bool(status)}


def check_repo(repo) -> Path:
    """``repo`` resolved, refused unless it holds gmmgp_app (a one-line ValueError)."""
    r = Path(repo).resolve()
    if not (r / "gmmgp_app" / "cli.py").is_file():
        raise ValueError(f"--repo {repo} holds no gmmgp_app/cli.py; give the checkout whose "
                         "code should map (default: this script's repository).")
    return r



# A small launcher measures the mapper: Linux hands a forked child the parent's
# high-water RSS (kept across exec), so the mapper must be forked from a small process.
LAUNCHER = (
    "import json, os, subprocess, sys, time\n"
    "t0 = time.perf_counter()\n"
    "p = subprocess.Popen(sys.argv[2:])\n"
    "_, status, ru = os.wait4(p.pid, 0)\n"
    "json.dump({'wall_s': time.perf_counter() - t0, 'peak_rss_mb': ru.ru_maxrss / 1024.0,\n"
    "           'returncode': os.waitstatus_to_exitcode(status)}, open(sys.argv[1], 'w'))\n")


def run_measured(cmd, env=None, cwd=None) -> dict:
    """Run ``cmd`` as a child of a small launcher; its wall time and its own peak RSS (MB)."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        rep = Path(tmp) / "rusage.json"
        with open(Path(tmp) / "out", "w+b") as fo, open(Path(tmp) / "err", "w+b") as fe:
            r = subprocess.run([sys.executable, "-c", LAUNCHER, str(rep), *map(str, cmd)],
                               env=env, cwd=cwd, stdout=fo, stderr=fe)
            fo.seek(0), fe.seek(0)
            out, err = fo.read().decode(errors="replace"), fe.read().decode(errors="replace")
        m = json.loads(rep.read_text()) if rep.is_file() else {"returncode": r.returncode}
    if r.returncode != 0 or m["returncode"] != 0:
        raise RuntimeError(f"{' '.join(map(str, cmd))} failed ({m['returncode']}):\n"
                           f"{err[-3000:]}")
    return {"wall_s": m["wall_s"], "peak_rss_mb": m["peak_rss_mb"], "stdout": out,
            "stderr": err}


def find_old_pythons() -> list:
    """Interpreters older than 3.11 on this machine (vdbfusion's wheels stop at 3.10)."""
    cands = []
    roots = [os.environ.get("PYENV_ROOT", ""), str(Path.home() / ".pyenv"), "/root/.pyenv"]
    for r in dict.fromkeys(x for x in roots if x):
        cands += sorted(glob.glob(f"{r}/versions/3.*/bin/python"), reverse=True)
    for v in ("3.10", "3.9", "3.8", "3.7"):
        w = shutil.which(f"python{v}")
        if w:
            cands.append(w)
    out = []
    for c in dict.fromkeys(cands):
        try:
            ver = subprocess.run([c, "-c", "import sys; print(*sys.version_info[:2])"],
                                 capture_output=True, text=True, timeout=30).stdout.split()
            ver = tuple(int(x) for x in ver)
        except (OSError, ValueError, subprocess.TimeoutExpired):
            continue
        if (3, 7) <= ver < (3, 11):
            out.append((ver, c))
    return [c for _, c in sorted(out, reverse=True)]


def vdbfusion_python(peers: Path, log) -> str | None:
    """A python with vdbfusion installed in ``peers/venv-*`` (made once), or None."""
    smoke = ("import numpy as np, vdbfusion; v = vdbfusion.VDBVolume(0.05, 0.3, False); "
             "v.integrate(np.random.rand(100, 3) + [3, 0, 0], np.zeros(3)); "
             "v.extract_triangle_mesh(False, 0.0)")

    def works(py):
        return subprocess.run([str(py), "-c", smoke], capture_output=True).returncode == 0

    for py in sorted(peers.glob("venv-*/bin/python")):
        if works(py):
            return str(py)
    for base in find_old_pythons():
        tag = Path(base).resolve().parent.parent.name
        venv = peers / f"venv-{tag}"
        log(f"vdbfusion: making a side environment {venv} from {base}")
        r = subprocess.run([base, "-m", "venv", str(venv)], capture_output=True, text=True)
        py = venv / "bin" / "python"
        if r.returncode != 0 or not py.exists():
            continue
        # its wheels are built against numpy 1: with numpy 2 integrate() segfaults
        r = subprocess.run([str(py), "-m", "pip", "install", "-q", "vdbfusion", "numpy<2"],
                           capture_output=True, text=True)
        if r.returncode == 0 and works(py):
            return str(py)
        shutil.rmtree(venv, ignore_errors=True)
    return None


# --------------------------------------------------------------------------- inputs
def make_inputs(work: Path, cases, density: float, subset: float, seed: int, kitti: Path,
                log) -> dict:
    """scan.npz (points, origins) per case, plus the exact mesh for synthetic ones."""
    from gmmgp_app.synth import write_scene
    from gmmgp_app.synth.io import save_scan_npz

    inputs = {}
    street = work / f"street_d{density:g}_s{seed}"
    if {"street", "street10"} & set(cases):
        if not (street / "scene.json").is_file():
            log(f"simulating the street at density {density:g} -> {street}")
            write_scene("street", street, density=density, seed=seed)
        inputs["street"] = {"scan": street / "scan.npz", "mesh": street / "mesh.ply"}
    if "street10" in cases:
        sub = work / f"street_d{density:g}_s{seed}_sub{subset:g}.npz"
        if not sub.is_file():
            with np.load(street / "scan.npz") as z:
                n = len(z["points"])
                idx = np.sort(np.random.default_rng(seed).choice(n, int(round(subset * n)),
                                                                 replace=False))
                save_scan_npz(sub, z["points"][idx], z["origins"][idx], z["labels"][idx])
        inputs["street10"] = {"scan": sub, "mesh": street / "mesh.ply"}
    if "kitti" in cases:
        if not kitti.is_file():
            log(f"kitti: {kitti} not found; skipping the KITTI case")
        else:
            out = work / f"kitti_{kitti.stem}.npz"
            if not out.is_file():
                from gmmgp_app.datasets import read_scan

                scan = read_scan(kitti)  # sensor frame; the sensor sits at its origin
                save_scan_npz(out, scan.points + scan.offset,
                              np.zeros_like(scan.points) if scan.origins is None
                              else scan.origins + scan.offset)
            inputs["kitti"] = {"scan": out, "mesh": None}
    return {c: inputs[c] for c in cases if c in inputs}


# --------------------------------------------------------------------------- metrics
def mesh_metrics(vertices, faces, scan_points, ref_mesh, n_samples: int, seed: int) -> dict:
    """The mesh's accuracy, completeness and chamfer distance
    (:func:`gmmgp_app.evaluation.surface_distance_samples`): against the exact mesh
    ``ref_mesh`` cropped to 10 cm of the scan points, or the scan points themselves."""
    from gmmgp_app.evaluation import Reference, surface_distance_samples

    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    if len(f) == 0:
        return {"faces": 0}
    if ref_mesh is not None:
        acc, comp = surface_distance_samples(v, f, Reference.from_mesh(*ref_mesh),
                                             n_samples=n_samples, crop_points=scan_points,
                                             crop_radius=0.1, oversample=8,
                                             rng=np.random.default_rng(seed))
    else:
        acc, comp = surface_distance_samples(v, f, Reference.from_points(scan_points),
                                             n_samples=n_samples,
                                             rng=np.random.default_rng(seed))
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                                axis=1).sum()
    return {
        "vertices": int(len(v)), "faces": int(len(f)), "area_m2": float(area),
        "acc_mean_mm": 1e3 * float(acc.mean()), "acc_rmse_mm": 1e3 * float(np.sqrt(np.mean(acc ** 2))),
        "acc_p95_mm": 1e3 * float(np.quantile(acc, 0.95)),
        "comp_mean_mm": 1e3 * float(comp.mean()),
        **{f"comp_{int(t * 100)}cm": float(np.mean(comp <= t)) for t in (0.01, 0.02, 0.05)},
        "chamfer_mm": 1e3 * 0.5 * float(acc.mean() + comp.mean()),
        "n_samples": [int(len(acc)), int(len(comp))],
    }


def read_ref_mesh(path: Path):
    import open3d as o3d

    m = o3d.io.read_triangle_mesh(str(path))
    return np.asarray(m.vertices, np.float64), np.asarray(m.triangles, np.int64)


# --------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default=",".join(CASES), help=f"subset of {','.join(CASES)}")
    ap.add_argument("--density", type=float, default=1.0, help="street scanner density")
    ap.add_argument("--subset", type=float, default=0.1, help="fraction for street10")
    ap.add_argument("--kitti", default=str(KITTI), help="KITTI Velodyne .bin")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=1, help="runs per mapper and case "
                    "(median quoted)")
    ap.add_argument("--samples", type=int, default=200_000, help="mesh samples per metric")
    ap.add_argument("--gmmgp-arg", action="append", default=[],
                    help="extra argument for 'gmmgp run' (repeatable)")
    ap.add_argument("--peers", default=str(ROOT / ".peers"), help="side environment folder")
    ap.add_argument("--out", default=str(ROOT / "out" / "bench"))
    ap.add_argument("--no-vdbfusion", action="store_true")
    ap.add_argument("--keep-runs", action="store_true",
                    help="keep each run's output folder (maps and meshes, 0.1-0.4 GB each) in "
                         "OUT/peers_work; by default they are removed once measured (the "
                         "generated input scans are kept and reused)")
    ap.add_argument("--repo", default=str(ROOT),
                    help="checkout whose gmmgp_app maps (default: this script's repository, "
                         f"{ROOT}); PYTHONPATH does not choose it")
    args = ap.parse_args(argv)
    try:
        repo = check_repo(args.repo)
    except ValueError as e:
        ap.error(str(e))

    from gmmgp_app._atomic import atomic_write_text
    from gmmgp_app.stages.surface import read_mesh_ply

    log = lambda *a: print(*a, file=sys.stderr, flush=True)  # noqa: E731
    out = Path(args.out)
    work = out / "peers_work"
    work.mkdir(parents=True, exist_ok=True)
    peers = Path(args.peers)
    peers.mkdir(parents=True, exist_ok=True)
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    bad = set(cases) - set(CASES)
    if bad:
        ap.error(f"unknown case(s) {sorted(bad)}; choose from {','.join(CASES)}")
    inputs = make_inputs(work, cases, args.density, args.subset, args.seed, Path(args.kitti), log)

    vdb_py, skipped = None, None
    if not args.no_vdbfusion:
        vdb_py = vdbfusion_python(peers, log)
        if vdb_py is None:
            skipped = ("VDBFusion skipped: no Python 3.7-3.10 interpreter with a vdbfusion "
                       "wheel on this machine (pyenv or python3.x on PATH)")
            log(skipped)
    runner = peers / "vdbfusion_runner.py"
    runner.write_text(RUNNER)

    log(f"gmmgp: the code of {repo}")
    results = {"cases": {}, "mapper": mapper_source(repo), "settings": {
        "vdbfusion": {"voxel_m": VOXEL, "sdf_trunc_m": TRUNC, "space_carving": False,
                      "fill_holes": False, "min_weight": 0.0, "origin_cell_m": ORIGIN_CELL},
        "gmmgp_args": args.gmmgp_arg, "repeats": args.repeats, "samples": args.samples},
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                    "load_avg_start": list(os.getloadavg())}}
    if skipped:
        results["vdbfusion_skipped"] = skipped
    for case, inp in inputs.items():
        with np.load(inp["scan"]) as z:
            pts = np.ascontiguousarray(z["points"], np.float64)
        ref = read_ref_mesh(inp["mesh"]) if inp["mesh"] else None
        res = {"n_points": int(len(pts)), "methods": {}}
        mappers = {"gmmgp": None}
        if vdb_py:
            mappers["vdbfusion"] = None
        for name in mappers:
            runs = []
            for r in range(args.repeats):
                d = work / f"{case}_{name}_{r}"
                shutil.rmtree(d, ignore_errors=True)
                if name == "gmmgp":
                    cmd, env, cwd = mapper_command(repo, inp["scan"], d, args.gmmgp_arg)
                else:
                    d.mkdir(parents=True)
                    cmd = [vdb_py, str(runner), str(inp["scan"]), str(d / "mesh.npz"),
                           str(VOXEL), str(TRUNC), str(ORIGIN_CELL)]
                    env, cwd = None, None
                log(f"{case}: {name} run {r + 1}/{args.repeats} ...")
                m = run_measured(cmd, env=env, cwd=cwd)
                if name == "gmmgp":
                    m["stages"] = json.loads((d / "summary.json").read_text())["seconds"]
                else:
                    m["stages"] = json.loads((d / "mesh.npz.json").read_text())["seconds"]
                log(f"  {m['wall_s']:.1f} s, {m['peak_rss_mb']:.0f} MB "
                    + " ".join(f"{k}={v:.2f}" for k, v in m["stages"].items()))
                runs.append((m, d))
            walls = [m["wall_s"] for m, _ in runs]
            med = int(np.argsort(walls)[len(walls) // 2])
            m, d = runs[med]
            if name == "gmmgp":
                mesh = read_mesh_ply(d / "mesh_gmmgp.ply")
                v, f = mesh.vertices, mesh.faces
            else:
                with np.load(d / "mesh.npz") as z:
                    v, f = z["vertices"], z["faces"]
            t0 = time.perf_counter()
            metrics = mesh_metrics(v, f, pts, ref, args.samples, args.seed)
            log(f"  metrics ({time.perf_counter() - t0:.0f} s): "
                + ", ".join(f"{k}={x:.3g}" for k, x in metrics.items()
                            if isinstance(x, float)))
            res["methods"][name] = {
                "wall_s": float(np.median(walls)), "wall_s_runs": walls,
                "peak_rss_mb": float(np.median([m["peak_rss_mb"] for m, _ in runs])),
                "peak_rss_mb_runs": [m["peak_rss_mb"] for m, _ in runs],
                "stages_s": m["stages"], "mesh": metrics}
            if not args.keep_runs:
                for _, d in runs:
                    shutil.rmtree(d, ignore_errors=True)
        results["cases"][case] = res
    results["machine"]["load_avg_end"] = list(os.getloadavg())
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "bench_peers.json", json.dumps(results, indent=2))
    md = markdown(results)
    atomic_write_text(out / "bench_peers.md", md)
    print(md)
    return 0


def markdown(results) -> str:
    lines = ["| case | points | mapper | wall s | peak RSS MB | acc mean / RMSE mm | "
             "within 1 / 2 / 5 cm % | chamfer mm | faces |",
             "|---|---|---|---|---|---|---|---|---|"]
    for case, res in results["cases"].items():
        for name, m in res["methods"].items():
            k = m["mesh"]
            if k.get("faces", 0) == 0:
                metr = "no mesh | - | - | 0"
            else:
                metr = (f"{k['acc_mean_mm']:.1f} / {k['acc_rmse_mm']:.1f} | "
                        f"{100 * k['comp_1cm']:.1f} / {100 * k['comp_2cm']:.1f} / "
                        f"{100 * k['comp_5cm']:.1f} | {k['chamfer_mm']:.1f} | {k['faces']}")
            lines.append(f"| {case} | {res['n_points']} | {name} | {m['wall_s']:.1f} | "
                         f"{m['peak_rss_mb']:.0f} | {metr} |")
    src = results.get("mapper") or {}
    notes = ["", f"gmmgp: the code of {src.get('repo', '?')} at {src.get('commit') or '?'}"
             + (" with uncommitted changes" if src.get("modified") else "") + ".",
             "", "Wall time and peak RSS of the whole process (read, map, mesh, write); "
             f"median of {results['settings']['repeats']} run(s). Accuracy: mesh samples to "
             "the exact mesh (KITTI: to the scan); completeness: observed exact surface "
             "(KITTI: scan points) within 1/2/5 cm of the mesh."]
    if "vdbfusion_skipped" in results:
        notes.append(results["vdbfusion_skipped"])
    return "\n".join(lines + notes) + "\n"


if __name__ == "__main__":
    sys.exit(main())
