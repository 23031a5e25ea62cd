"""Session 8 (speed-16o): the lookup loop of _cover_pairs alone, binary search vs hash table,
and the new _cover_pairs, on the demo queries of bench_cover.py (CPU s, 5 runs, one process):
    NUMBA_NUM_THREADS=1 PYTHONPATH=$PWD python docs/speed/s8_16o/split_lookups.py D/map
"""
import resource, numpy as np
from numba import njit, prange
import gmmgp_app.pipeline as P
from gmmgp_app.stages import octree as O
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF); return r.ru_utime + r.ru_stime
@njit(parallel=True)
def lookups(lo, hi, tk, tv, packed, hashed):
    n = lo.shape[0]; s = 0
    tot = np.zeros(n, np.int64)
    for i in prange(n):
        m = 0
        for a in range(lo[i, 0], hi[i, 0] + 1):
            for b in range(lo[i, 1], hi[i, 1] + 1):
                for c in range(lo[i, 2], hi[i, 2] + 1):
                    j = O._hfind(tk, tv, a, b, c) if hashed else O._find(packed, a, b, c)
                    m += j
        tot[i] = m
    return tot
smap = P.load_map(__import__('sys').argv[1])
pts = np.load('assets/demo_street.npz')['points'] - smap.offset
rng = np.random.default_rng(0)
q = np.concatenate([pts + rng.normal(0, 0.05, pts.shape) for _ in range(4)])
g = smap.gp.grid; h = g.block_size; half = g.half_extent
lo = np.ascontiguousarray(np.ceil((q - half) / h - 0.5).astype(np.int64)); hi = np.ascontiguousarray(np.floor((q + half) / h - 0.5).astype(np.int64))
tk, tv = O._hash_table(g._packed)
for hashed in (False, True): lookups(lo[:5], hi[:5], tk, tv, g._packed, hashed)
O._cover_pairs(lo[:10], hi[:10], len(g._packed), tk, tv)
res = {'search': [], 'hash': [], 'cover_pairs': []}
for _ in range(5):
    for hashed in (False, True):
        t = cpu(); lookups(lo, hi, tk, tv, g._packed, hashed); res['hash' if hashed else 'search'].append(cpu() - t)
    t = cpu(); O._cover_pairs(lo, hi, len(g._packed), tk, tv); res['cover_pairs'].append(cpu() - t)
print({k: (round(float(np.median(v)), 3), [round(x, 3) for x in v]) for k, v in res.items()})
