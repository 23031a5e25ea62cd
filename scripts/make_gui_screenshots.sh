#!/usr/bin/env bash
# Make the README screenshots of the desktop app (gmmgp view) on the bundled demo scan.
#
#   scripts/make_gui_screenshots.sh            # writes docs/gui_*.png
#   OUT=/tmp/shots scripts/make_gui_screenshots.sh
#
# The app runs headless under its own Xvfb display (xvfb-run), driven by a --script of
# steps (see gmmgp_app/viz/gui_script.py); each PNG is the whole window, side panel included,
# grabbed from the X server. With Mesa's CPU Vulkan driver one frame sometimes takes
# minutes on a loaded machine, so each attempt has a time limit and is retried.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
OUT=${OUT:-docs}
SIZE=${SIZE:-1280x800}
TRIES=${TRIES:-4}
LIMIT=${LIMIT:-300}
command -v xvfb-run >/dev/null || { echo "xvfb-run not found (apt-get install xvfb)" >&2; exit 2; }
mkdir -p "$OUT"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# Camera: oblique view of the street, from the road side, slightly above the cars.
"$PY" - "$work" "$OUT" <<'EOF'
import json, sys
from pathlib import Path
work, out = Path(sys.argv[1]), Path(sys.argv[2]).resolve()
shot = lambda name: {"screenshot": str(out / f"gui_{name}.png"), "window": True}
steps = [
    {"stage": "hgmm"}, {"level": 2}, shot("hgmm_level2"),
    {"level": 3}, shot("hgmm_level3"),
    {"stage": "gp"}, shot("gp_points"),
    {"stage": "surface"}, {"colour_by_variance": True}, {"probe": "center"},
    shot("surface_variance"),
    {"state": str(work / "state.json")}, {"quit": True},
]
(work / "steps.json").write_text(json.dumps(steps))
EOF

for try in $(seq 1 "$TRIES"); do
  echo "attempt $try: gmmgp view assets/demo_street.npz ($SIZE, limit ${LIMIT}s)"
  if timeout -k 10 "$LIMIT" xvfb-run -a -s "-screen 0 1600x1000x24" \
       "$PY" -m gmmgp_app.viz.gui assets/demo_street.npz --size "$SIZE" \
       --script "$work/steps.json"; then
    # 256-colour palette PNGs: a quarter of the bytes, no visible change for flat renders.
    "$PY" -c 'import sys; from PIL import Image
for f in sys.argv[1:]:
    Image.open(f).convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT).save(f, optimize=True)' "$OUT"/gui_*.png
    ls -l "$OUT"/gui_*.png
    exit 0
  fi
  echo "attempt $try failed or timed out; retrying" >&2
done
echo "no attempt finished within ${LIMIT}s" >&2
exit 1
