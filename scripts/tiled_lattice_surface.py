"""Surface CPU seconds of a saved tiled map (or run folder) meshed with every tile's
surface.lattice_field set to each of FIELDS in turn ("map,far,map,far"), with the
vertices' |mean| / voxel of the full stitched map at 20k seeded vertices; JSON rows.

    PYTHONPATH=$PWD .venv/bin/python scripts/tiled_lattice_surface.py MAP_DIR map,far,map,far OUT.json
"""
import copy, json, resource, sys, time
import numpy as np
from gmmgp_app.tiling import TiledMap
from gmmgp_app.tiling.tiled_map import load_any_map

def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime

tm0 = load_any_map(sys.argv[1])
order = sys.argv[2].split(",")
out = []
for field in order:
    tiles = {}
    for k, t in tm0.tiles.items():
        tiles[k] = copy.copy(t)
        tiles[k].config = t.config.replace({"surface.lattice_field": field})
    tm = TiledMap(tm0.spec, tiles, tm0.config, tm0.method, offset=tm0.offset, owners=tm0.owners)
    import os
    load = os.getloadavg()[0]
    c0, w0 = cpu(), time.perf_counter()
    mesh = tm.extract_surface()
    c1, w1 = cpu(), time.perf_counter()
    rng = np.random.default_rng(0)
    sel = rng.choice(len(mesh.vertices), min(20000, len(mesh.vertices)), replace=False)
    vox = tm.surface_voxel()
    r = np.abs(tm.predict_mean(mesh.vertices[sel])) / vox
    row = dict(field=field, cpu_s=c1 - c0, wall_s=w1 - w0, load_start=load,
               vertices=len(mesh.vertices), faces=len(mesh.faces), voxel=vox,
               m_over_voxel_median=float(np.median(r)), m_over_voxel_p99=float(np.quantile(r, .99)))
    print(json.dumps(row), flush=True)
    out.append(row)
    
json.dump(out, open(sys.argv[3], "w"), indent=1)
