#!/usr/bin/env bash
# Make the README screenshots of the desktop app (gmmgp view) on the bundled demo scan,
# through the app's own offscreen path: `gmmgp view TARGET --screenshot PNG` renders one
# frame (Open3D's OffscreenRenderer: the window's layers, materials and camera), writes it
# and exits. No window, no frame loop to wait for, no retries.
#
#   scripts/make_gui_screenshots.sh            # writes docs/gui_*.png
#   OUT=/tmp/shots scripts/make_gui_screenshots.sh
#
# It maps the demo scan (untiled and in 15 m tiles) into a temporary folder first, then
# renders: HGMM levels 2 and 3 and the GP points of the run folder, the surface the run
# wrote, a split-threshold comparison (the GP points of c* 0.01 beside those of c* 0.03),
# the tiled map's stitched surface and a check result coloured by z (a second simulated
# pass of the demo street with a van parked in it, `gmmgp check`ed against the map).
# It prints each run's times and counts (the figures the README quotes).
# The OffscreenRenderer needs a display like the window: xvfb-run.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
OUT=${OUT:-docs}
SIZE=${SIZE:-1280x800}
command -v xvfb-run >/dev/null || { echo "xvfb-run not found (apt-get install xvfb)" >&2; exit 2; }
mkdir -p "$OUT"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
gmmgp() { "$PY" -m gmmgp_app.cli "$@"; }
view() { local t0=$SECONDS; xvfb-run -a -s "-screen 0 1600x1000x24" "$PY" -m gmmgp_app.cli view "$@" --size "$SIZE"; echo "  ($((SECONDS - t0)) s)"; }

figures() {  # the figures of a run folder's summary.json (single or tiled map)
  "$PY" -c 'import json, sys
s = json.load(open(sys.argv[1] + "/summary.json")); c = s.get("counts", {})
sec = ", ".join(f"{k} {v:.1f}" for k, v in s.get("seconds", {}).items())
if s.get("tiled"):
    t, size, n = s.get("tile_seconds", {}), s.get("tile_spec", {}).get("size"), s.get("n_tiles")
    absorbed, skipped, mesh = s.get("n_absorbed_tiles"), s.get("n_skipped_tiles"), c.get("surface")
    med, top = t.get("median", 0.0), t.get("max", 0.0)
    print(f"{sys.argv[1]}: tiled ({size} m tiles: {n}, {absorbed} absorbed, {skipped} skipped): "
          f"seconds: {sec}; per tile median {med:.1f}, max {top:.1f}; mesh {mesh}")
else:
    leaves, gp, mesh = c.get("hgmm", {}).get("leaves"), c.get("gp", {}).get("n_points"), c.get("surface")
    print(f"{sys.argv[1]}: seconds: {sec}; leaves {leaves}, GP points {gp}, mesh {mesh}")' "$1"
}
gmmgp run assets/demo_street.npz --out "$work/demo" -q
figures "$work/demo"
gmmgp run assets/demo_street.npz --out "$work/tiled" --tile-size 15 -q
figures "$work/tiled"
# a second pass of the demo street (other noise, a van parked at y = -1.5 m), checked
"$PY" -c 'import sys
from gmmgp_app.synth import save_scan_npz, scan_scene
scan, _ = scan_scene("street_van", density=0.08, seed=1, lane_y=-1.5)
save_scan_npz(sys.argv[1], scan.points, scan.origins)' "$work/second.npz"
gmmgp check "$work/second.npz" --map "$work/demo/map" --out "$work/check"
view "$work/demo" --stage hgmm --level 2 --screenshot "$OUT/gui_hgmm_level2.png"
view "$work/demo" --stage hgmm --level 3 --screenshot "$OUT/gui_hgmm_level3.png"
view "$work/demo" --stage gp --screenshot "$OUT/gui_gp_points.png"
view "$work/demo" --stage surface --screenshot "$OUT/gui_surface.png"
# the GP stage, and below the HGMM stage (two sets of lit ellipsoids: they stalled the CPU
# renderer for over 15 min until lit meshes got texture coordinates, see gui_geometry._zero_uvs)
view assets/demo_street.npz --stage gp --compare hgmm.split_threshold=0.03 \
  --screenshot "$OUT/gui_compare_threshold.png"
# the same comparison on the HGMM stage (level 3): the leaves of both runs side by side
view assets/demo_street.npz --stage hgmm --level 3 --compare hgmm.split_threshold=0.03 \
  --screenshot "$OUT/gui_compare_hgmm.png"
view "$work/tiled" --stage surface --screenshot "$OUT/gui_tiled_surface.png"
view "$work/check" --screenshot "$OUT/gui_check_z.png"
# 256-colour palette PNGs: a quarter of the bytes, no visible change for flat renders.
"$PY" -c 'import sys; from PIL import Image
for f in sys.argv[1:]:
    Image.open(f).convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT).save(f, optimize=True)' \
  "$OUT"/gui_hgmm_level2.png "$OUT"/gui_hgmm_level3.png "$OUT"/gui_gp_points.png \
  "$OUT"/gui_surface.png "$OUT"/gui_compare_threshold.png "$OUT"/gui_tiled_surface.png \
  "$OUT"/gui_check_z.png "$OUT"/gui_compare_hgmm.png
ls -l "$OUT"/gui_*.png
