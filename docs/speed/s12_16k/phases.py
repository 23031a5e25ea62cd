import sys, time, math, numpy as np, numba as nb
nb.set_num_threads(1)
from gmmgp_app.pipeline import load_map
from gmmgp_app.stages import knn as K
smap = load_map(sys.argv[1]); z = np.load(sys.argv[2]); far = smap.far
kn = K.GridKNN(far.points, far.k, tree=far.tree)
x = np.ascontiguousarray(z[sys.argv[3] if len(sys.argv) > 3 else "lat"])
g = kn.group * kn.cell
c = np.floor(x / g).astype(np.int64); c -= c.min(0); dims = c.max(0) + 1
key = (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]
qorder = np.argsort(key, kind="stable"); ks = key[qorder]
gptr = np.r_[np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]]), len(ks)].astype(np.int64)
G = len(gptr) - 1

@nb.njit
def centre(x, qorder, gptr, gcell, k, cell, lo, dims, tk, ts, te, pts, max_ring):
    G = len(gptr) - 1
    bd = np.empty(k); bi = np.empty(k, np.int64); D = np.full(G, -1.0)
    for g in range(G):
        q0 = qorder[gptr[g]]
        b0 = math.floor(x[q0, 0] / gcell); b1 = math.floor(x[q0, 1] / gcell); b2 = math.floor(x[q0, 2] / gcell)
        if K._shell_knn((b0 + 0.5) * gcell, (b1 + 0.5) * gcell, (b2 + 0.5) * gcell, k, cell, lo, dims, tk, ts, te, pts, max_ring, bd, bi):
            D[g] = bd[k - 1]
    return D

@nb.njit
def full(x, qorder, gptr, gcell, k, cell, lo, dims, tk, ts, te, pts, order, max_ring, cap, colk, col0, col1, zc, stop):
    G = len(gptr) - 1
    mask = len(tk) - 1
    half = gcell * math.sqrt(3.0) / 2
    bd = np.empty(k); bi = np.empty(k, np.int64)
    cand = np.empty(cap, np.int64); cd = np.empty(cap); cs = np.empty(cap, np.int64); cdist = np.empty(cap)
    px = np.empty(cap); py = np.empty(cap); pz = np.empty(cap)
    dist = np.empty((x.shape[0], k)); idx = np.empty((x.shape[0], k), np.int64); done = np.zeros(x.shape[0], np.bool_)
    tot = 0
    for g in range(G):
        q0 = qorder[gptr[g]]
        b0 = math.floor(x[q0, 0] / gcell); b1 = math.floor(x[q0, 1] / gcell); b2 = math.floor(x[q0, 2] / gcell)
        cx = (b0 + 0.5) * gcell; cy = (b1 + 0.5) * gcell; cz = (b2 + 0.5) * gcell
        n = K._group_candidates(b0, b1, b2, cx, cy, cz, gcell, half, k, cell, lo, dims, tk, ts, te, pts, max_ring, cap, mask, bd, bi, cand, cd, cs, cdist, px, py, pz, colk, col0, col1, zc)
        if n < 0: continue
        tot += n
        if stop: continue
        K._group_members(g, x, qorder, gptr, cx, cy, cz, gcell, k, order, n, cs, cdist, px, py, pz, bd, bi, dist, idx, done)
    return tot

args = (x, qorder, gptr, g, kn.k, kn.cell, kn.lo, kn.dims, kn.table_keys, kn.table_start, kn.table_end, kn.sorted_points)
centre(*args, kn.max_ring); full(*args, kn.order, kn.max_ring, kn.max_candidates, *kn.columns, True)
for rep in range(2):
    t = time.process_time(); D = centre(*args, kn.max_ring); t1 = time.process_time() - t
    t = time.process_time(); n = full(*args, kn.order, kn.max_ring, kn.max_candidates, *kn.columns, True); t2 = time.process_time() - t
    t = time.process_time(); n = full(*args, kn.order, kn.max_ring, kn.max_candidates, *kn.columns, False); t3 = time.process_time() - t
    print(f"G {G} ok {(D>=0).sum()} cand total {n}: centre {t1:.3f}, centre+gather+sort {t2:.3f}, +members {t3:.3f}")
D = centre(*args, kn.max_ring)
okg = np.flatnonzero(D >= 0); bad = np.flatnonzero(D < 0)
def sub(sel):
    gp2 = np.r_[gptr[sel], 0]  # only first member matters for centre
    qo = qorder[gptr[sel]]
    gp = np.arange(len(sel) + 1, dtype=np.int64)
    return (x, qo, gp) + args[3:]
for name, sel in (("ok", okg), ("fail", bad)):
    a = sub(sel); centre(*a, kn.max_ring)
    t = time.process_time(); centre(*a, kn.max_ring); print(name, len(sel), round(time.process_time() - t, 3))
t = time.process_time(); kn.tree.query((np.floor(x[qorder[gptr[:-1]]] / g) + 0.5) * g, k=kn.k, workers=1); print("kd all centres", round(time.process_time() - t, 3))
