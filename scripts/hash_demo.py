"""Print sha256 hashes of a map run's arrays and meshes (bit-for-bit comparison of two runs).

Usage:
    python -m gmmgp_app.cli run assets/demo_street.npz --out /tmp/demo_a
    python scripts/hash_demo.py /tmp/demo_a            # one line per array / mesh file
    python scripts/hash_demo.py /tmp/demo_a /tmp/demo_b  # compare: exit 1 on any difference

Each array of the saved map (either format: ``map/arrays/*.npy`` or a format-1
``map/arrays.npz``, labelled ``array:NAME`` in both so runs of either compare) is hashed
over its dtype, shape and bytes (so a reshaped or re-typed array with equal bytes still
differs); each ``mesh_*.ply`` over its file bytes.
"""
from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gmmgp_app.map_io import read_map_folder  # noqa: E402


def hashes(out_dir: str | Path) -> dict[str, str]:
    """{name: sha256 hex} for every array of out_dir/map and every out_dir/mesh_*.ply."""
    out = Path(out_dir)
    result: dict[str, str] = {}
    arrays = read_map_folder(out / "map")[1]
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h = hashlib.sha256()
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
        result[f"array:{name}"] = h.hexdigest()
    for ply in sorted(out.glob("mesh_*.ply")):
        result[ply.name] = hashlib.sha256(ply.read_bytes()).hexdigest()
    return result


def main(argv: list[str]) -> int:
    if len(argv) not in (1, 2):
        print(__doc__, file=sys.stderr)
        return 2
    first = hashes(argv[0])
    if len(argv) == 1:
        for k, v in first.items():
            print(f"{v}  {k}")
        return 0
    second = hashes(argv[1])
    diff = sorted(k for k in first.keys() | second.keys() if first.get(k) != second.get(k))
    print(json.dumps({"compared": len(first.keys() | second.keys()), "different": diff}, indent=1))
    return 1 if diff else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
