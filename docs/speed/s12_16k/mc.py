import sys, time, numpy as np
import skimage.measure as M
from gmmgp_app.pipeline import load_map
smap = load_map(sys.argv[1])
vols = []
orig = M.marching_cubes
def grab(vol, level=0.0, mask=None, allow_degenerate=False):
    vols.append((vol.copy(), mask.copy()))
    return orig(vol, level=level, mask=mask, allow_degenerate=allow_degenerate)
M.marching_cubes = grab
smap.extract_surface(overlap=False)
M.marching_cubes = orig
print("blocks", len(vols))
def active_hi(vol):
    neg = vol <= 0; pos = vol >= 0
    # a cell is active if its 8 corners include a <=0 and a >=0 node
    def cellany(a):
        c = a[:-1, :-1, :-1].copy()
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    c |= a[dx:a.shape[0]-1+dx, dy:a.shape[1]-1+dy, dz:a.shape[2]-1+dz]
        return c
    act = cellany(neg) & cellany(pos)
    if not act.any(): return None
    hi = [np.flatnonzero(act.any(axis=tuple(j for j in range(3) if j != ax))).max() + 2 for ax in range(3)]
    lo = [np.flatnonzero(act.any(axis=tuple(j for j in range(3) if j != ax))).min() for ax in range(3)]
    return hi, lo
full = crop = 0.0; frac = []; fracl = []; same = 0; n = 0
for vol, mask in vols:
    t = time.process_time()
    try: a = orig(vol, level=0.0, mask=mask, allow_degenerate=False)
    except (ValueError, RuntimeError): a = None
    full += time.process_time() - t
    r = active_hi(vol)
    if r is None:
        same += a is None; continue
    hi, lo = r
    s = np.s_[:hi[0], :hi[1], :hi[2]]
    frac.append(np.prod(hi) / vol.size); fracl.append(np.prod(np.array(hi) - lo) / vol.size)
    t = time.process_time()
    try: b = orig(np.ascontiguousarray(vol[s]), level=0.0, mask=np.ascontiguousarray(mask[s]), allow_degenerate=False)
    except (ValueError, RuntimeError): b = None
    crop += time.process_time() - t
    n += 1
    if a is None or b is None: same += (a is None) == (b is None)
    else: same += all(np.array_equal(x, y) for x, y in zip(a[:2], b[:2]))
print(f"mc full {full:.3f} s, upper-cropped {crop:.3f} s; identical v,f in {same} of {len(vols)}; mean volume fraction upper crop {np.mean(frac):.3f}, both ends {np.mean(fracl):.3f}")
