"""Cost of one 1280x800 frame of each scene the app shows on the demo scan.

Maps the demo scan to the surface, then renders each scene (the app's layers, materials,
lighting and default camera) with Open3D's OffscreenRenderer three times after a first
upload frame and prints one JSON line per scene: the median wall time and the median
CPU seconds of the rasterizer threads (llvmpipe-*), with nothing else computing.

    xvfb-run -a python scripts/bench_scene_frames.py ["hgmm L3" "gp all" ...]

Measured 2026-11-24 (2 shared cores, load 5-8 from other jobs, rasterizer CPU s per
frame): empty 0.11; the scan's 102,188 points 0.34; HGMM level 0 0.5, level 2 1.33,
level 3 2.83 (512 lit leaves of 224 triangles, 187 split wireframes); GP points 0.61;
the GP stage with its 58,595 blocks as "unlitLine" lines (703,140 segments) 16.5,
as 1-pixel lines ("defaultUnlit") 1.3 (the app now); the surface (470,267 faces, voxel
0.1 m) 3.84. Wide lines cost a quad per segment: the split wireframes of level 3
1.06 -> 0.22 s as 1-pixel lines.
"""
import glob, json, os, sys, time
import numpy as np
import open3d.visualization.rendering as R
from gmmgp_app.viz.gui_model import ViewerModel
from gmmgp_app.viz.gui_screenshot import SceneState, _compute_until, camera_pose
from gmmgp_app.viz.gui_layers import materials, set_lighting

def cpu():
    hz = os.sysconf("SC_CLK_TCK"); d = {}
    for t in glob.glob(f"/proc/{os.getpid()}/task/*"):
        name = open(t + "/comm").read().strip(); st = open(t + "/stat").read().rsplit(")", 1)[1].split()
        k = "llvmpipe" if name.startswith("llvmpipe") else "other"
        d[k] = d.get(k, 0) + (int(st[11]) + int(st[12])) / hz
    return d

m = ViewerModel.open("assets/demo_street.npz", voxel_size=0.1)
m.results = _compute_until(m, "prepare", "surface")
r = m.results
print("faces", len(r.mesh.faces), "verts", len(r.mesh.vertices), file=sys.stderr)
ren = R.OffscreenRenderer(1280, 800)
sc = ren.scene; sc.set_background([1, 1, 1, 1]); sc.show_axes(False); sc.view.set_post_processing(False)
set_lighting(sc, R); mats = materials(R)
lo, hi, c, eye = camera_pose(r.scan.points)
ext = float(np.linalg.norm(hi - lo)); dist = float(np.linalg.norm(eye - c))
ren.setup_camera(50.0, c.astype(np.float32), eye.astype(np.float32), np.array([0, 0, 1], np.float32), 1e-3 * dist, dist + 4 * ext)
cases = [("empty", "scan", 0, []), ("points", "hgmm", 0, ["points"]),
         ("hgmm L0", "hgmm", 0, ["points", "ellipsoids"]), ("hgmm L2", "hgmm", 2, ["points", "ellipsoids"]),
         ("hgmm L3", "hgmm", 3, ["points", "ellipsoids"]), ("hgmm L4", "hgmm", 4, ["points", "ellipsoids"]),
         ("ell L3 only", "hgmm", 3, ["ellipsoids"]),
         ("gp pts", "gp", 0, ["points", "gp_points"]), ("blocks only", "gp", 0, ["blocks"]),
         ("gp all", "gp", 0, ["points", "gp_points", "blocks"]), ("surface", "surface", 0, ["mesh"])]
only = sys.argv[1:] or None
for label, stage, level, layers in cases:
    if only and label not in only: continue
    sc.clear_geometry()
    st = SceneState(m, stage, level, layers=layers)
    ntri = 0
    for name in layers:
        key, build, mat, _ = st.layer_geometry(name)
        if key is None: continue
        g = build(); parts = g if isinstance(g, dict) else {name: g}
        for gn, gg in parts.items():
            sc.add_geometry(gn, gg, mats[gn if mat is None else mat])
            ntri += len(getattr(gg, "triangles", [])) or len(getattr(gg, "lines", [])) or len(getattr(gg, "points", []))
    ren.render_to_image()  # first frame (upload)
    res = []
    for _ in range(3):
        c0, t0 = cpu(), time.perf_counter()
        ren.render_to_image()
        c1 = cpu()
        res.append((time.perf_counter() - t0, c1["llvmpipe"] - c0["llvmpipe"]))
    w = sorted(x[0] for x in res)[1]; l = sorted(x[1] for x in res)[1]
    print(json.dumps({"scene": label, "primitives": ntri, "wall_s": round(w, 3), "llvmpipe_cpu_s": round(l, 3), "load": os.getloadavg()[0]}), flush=True)
