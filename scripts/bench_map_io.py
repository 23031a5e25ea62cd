"""Save and load one map in format 1 (``arrays.npz``, until session 10) and format 2 (one
``.npy`` per array), alternated, in one process: wall and CPU seconds, medians.

    PYTHONPATH=$PWD .venv/bin/python scripts/bench_map_io.py OUT/map --repeats 3

The map folder is loaded once (either format); each round then writes it as format 1
(``np.savez``, as main wrote it) and as format 2 (``SurfaceMap.save``) into a temporary
folder beside ``--work``, and loads both with ``load_map`` (the whole map object, not just
the arrays) and with the bare array read (``map_io.read_map_folder``). Checks that every
array loads back bit for bit from both.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def write_format_1(directory: Path, smap) -> None:
    """The folder as main wrote it until session 10 (format 1)."""
    import numpy as np

    from gmmgp_app._atomic import atomic_dir

    arrays, meta = smap._saved_contents()
    with atomic_dir(directory) as tmp:
        np.savez(tmp / "arrays.npz", **arrays)
        (tmp / "map.json").write_text(json.dumps({"format_version": 1, **meta}, indent=2))


def timed(fn):
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t, time.process_time() - c


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("map")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--work", default=None, help="folder for the copies (default: temp)")
    args = ap.parse_args(argv)
    import numpy as np

    from gmmgp_app.map_io import read_map_folder
    from gmmgp_app.pipeline import load_map

    smap = load_map(args.map)
    ref = smap.to_arrays()
    nbytes = sum(a.nbytes for a in ref.values())
    work = Path(tempfile.mkdtemp(dir=args.work, prefix="bench_map_io_"))
    rows = {k: [] for k in ("save 1", "save 2", "load_map 1", "load_map 2",
                            "arrays 1", "arrays 2")}
    try:
        for r in range(args.repeats):
            for fmt in (1, 2):
                d = work / f"f{fmt}"
                shutil.rmtree(d, ignore_errors=True)
                writer = (lambda: write_format_1(d, smap)) if fmt == 1 else \
                    (lambda: smap.save(d))
                rows[f"save {fmt}"].append(timed(writer)[1:])
            for fmt in (1, 2):
                d = work / f"f{fmt}"
                back, *t = timed(lambda: load_map(d))
                rows[f"load_map {fmt}"].append(t)
                arrays, *t = timed(lambda: read_map_folder(d)[1])
                rows[f"arrays {fmt}"].append(t)
                got = back.to_arrays()
                assert list(got) == list(ref) and all(
                    got[k].dtype == ref[k].dtype and got[k].shape == ref[k].shape
                    and np.array_equal(got[k], ref[k], equal_nan=got[k].dtype.kind == "f")
                    for k in ref), f"format {fmt}: arrays differ"
                del back, arrays, got
    finally:
        shutil.rmtree(work, ignore_errors=True)
    med = statistics.median
    print(f"map {args.map}: {len(ref)} arrays, {nbytes / 2**20:.0f} MiB; medians of "
          f"{args.repeats} (runs), wall / CPU s")
    for k, v in rows.items():
        print(f"  {k:<11} wall {med(w for w, _ in v):6.3f} ({' '.join(f'{w:.3f}' for w, _ in v)})"
              f"  CPU {med(c for _, c in v):6.3f} ({' '.join(f'{c:.3f}' for _, c in v)})")
    print("every array loaded back bit for bit from both formats")
    return 0


if __name__ == "__main__":
    sys.exit(main())
