"""Cost of one offscreen frame on this machine's renderer, per thread (issue 18's stalls).

Renders a sphere of N triangles with Open3D's OffscreenRenderer (Filament; on a machine
without a GPU: Mesa's lavapipe/llvmpipe) several times and prints one JSON line per
frame: wall time and CPU seconds per thread (main, llvmpipe-*, FEngine::loop).

    python scripts/bench_render_frames.py RES WxH FRAMES      # e.g. 40 640x480 3
    COLOURS=grey|random|jitter|gradient SHADER=defaultUnlit python scripts/bench_render_frames.py 40 640x480 3
    UVS=none|zero|planar COLOURS=grey python scripts/bench_render_frames.py 40 640x480 2

RES is Open3D's create_sphere resolution (40: 6240 triangles). Measured on 2 shared cores
(load 5-9), 6240 triangles at 640x480, rasterizer CPU per frame: no colours 1.3 s,
random colours 1.4 s, grey 0.75 lit 28 s (unlit 5.4 s), grey +- 0.004 26 s, z gradient 16 s;
but 360 triangles at 320x240 without colours took 0.2 s once and 30 s (89.6 s wall) later:
the same frame's cost varies by 100x between processes, so compare within one session.

UVS gives the sphere texture coordinates (the lit material samples its placeholder
texture maps at them). 2026-11-23, load ~7, grey, lit, 6240 triangles at 640x480,
rasterizer CPU per frame (both threads): none 1.9 s and 1.1 s (two sessions),
zero 0.2 s, planar 0.2 s. The app's lit meshes get zero coordinates
(gui_geometry._zero_uvs).
"""

import glob
import json
import os
import sys
import time

import numpy as np


def _cpu_by_thread() -> dict:
    hz = os.sysconf("SC_CLK_TCK")
    d = {}
    for t in glob.glob(f"/proc/{os.getpid()}/task/*"):
        try:
            name = open(t + "/comm").read().strip()
            st = open(t + "/stat").read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        d[name] = d.get(name, 0.0) + (int(st[11]) + int(st[12])) / hz
    return d


def main(argv):
    import open3d as o3d
    import open3d.visualization.rendering as R

    res, size, n = int(argv[0]), argv[1], int(argv[2])
    w, h = map(int, size.split("x"))
    ren = R.OffscreenRenderer(w, h)
    ren.scene.view.set_post_processing(False)
    m = o3d.geometry.TriangleMesh.create_sphere(0.5, res)
    m.compute_vertex_normals()
    nv, rng = len(m.vertices), np.random.default_rng(0)
    colours = os.environ.get("COLOURS", "none")
    cols = {"grey": lambda: np.full((nv, 3), 0.75),
            "random": lambda: rng.uniform(0, 1, (nv, 3)),
            "jitter": lambda: 0.75 + rng.uniform(-0.004, 0.004, (nv, 3)),
            "gradient": lambda: np.column_stack([0.5 + np.asarray(m.vertices)[:, 2]] * 3)}
    if colours in cols:
        m.vertex_colors = o3d.utility.Vector3dVector(cols[colours]())
    uvs = os.environ.get("UVS", "none")
    if uvs != "none":
        # texture coordinates per triangle corner: "zero" (all 0) or "planar" (x, z)
        v = np.asarray(m.vertices)[np.asarray(m.triangles).reshape(-1)]
        uv = np.zeros((len(v), 2)) if uvs == "zero" else v[:, [0, 2]] + 0.5
        m.triangle_uvs = o3d.utility.Vector2dVector(uv)
    mat = R.MaterialRecord()
    mat.shader = os.environ.get("SHADER", "defaultLit")
    ren.scene.add_geometry("m", m, mat)
    ren.setup_camera(50, [0, 0, 0], [0, -2, 1], [0, 0, 1])
    for i in range(n):
        c0, t0 = _cpu_by_thread(), time.perf_counter()
        ren.render_to_image()
        wall, c1 = time.perf_counter() - t0, _cpu_by_thread()
        cpu = {k: round(c1[k] - c0.get(k, 0.0), 2) for k in c1 if c1[k] - c0.get(k, 0.0) > 0.005}
        print(json.dumps({"frame": i, "triangles": len(m.triangles), "size": size,
                          "colours": colours, "uvs": uvs, "shader": mat.shader, "wall_s": round(wall, 2),
                          "cpu_s": cpu, "load": round(os.getloadavg()[0], 2),
                          "lp_num_threads": os.environ.get("LP_NUM_THREADS")}), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
