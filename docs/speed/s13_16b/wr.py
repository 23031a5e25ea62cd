import numpy as np, time, os, resource
a = np.random.rand(306_000_000 // 8)
def cpu(): r = resource.getrusage(resource.RUSAGE_THREAD); return r.ru_utime + r.ru_stime
for how in ("np.save", "os.write", "np.save", "os.write"):
    p = f"/tmp/speed-16b/w_{how}.npy"
    if os.path.exists(p): os.unlink(p)
    t, c = time.perf_counter(), cpu()
    if how == "np.save":
        np.save(p, a)
    else:
        fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        mv = memoryview(a).cast("B"); off = 0
        while off < len(mv):
            off += os.write(fd, mv[off:off + (64 << 20)])
        os.close(fd)
    print(how, f"wall {time.perf_counter()-t:.3f} cpu {cpu()-c:.3f}")
    os.unlink(p)
