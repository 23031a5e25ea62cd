#!/usr/bin/env python
"""Render a rerun recording (.rrd) to a PNG without a display.

``rerun FILE.rrd --headless --screenshot-to out.png`` takes its screenshot as soon
as the window exists, often before a large recording (meshes of a few 100k
vertices) has loaded: the views come out empty. This script spawns a headless
viewer, opens the recording, moves the time cursor (default: the end of the
``stage`` timeline, so every stage is shown), waits until the viewer has had time
to draw, and saves the whole window.

Needs a Vulkan device or Mesa's llvmpipe (installed by scripts/setup.sh).

Examples
--------
    python scripts/render_rrd.py out/demo/demo.rrd docs/rerun_demo.png
    python scripts/render_rrd.py out/demo/demo.rrd /tmp/level1.png --timeline level --time 1
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("rrd", help="recording to render")
    ap.add_argument("png", help="output PNG (whole viewer window)")
    ap.add_argument("--timeline", default="stage", help="timeline to move (default: stage)")
    ap.add_argument("--time", type=int, help="sequence value (default: the timeline's end)")
    ap.add_argument("--wait", type=float, default=8.0,
                    help="seconds to let the viewer draw before the screenshot (default 8)")
    ap.add_argument("--port", type=int, default=9877, help="gRPC port of the viewer")
    args = ap.parse_args(argv)
    rrd = Path(args.rrd)
    if not rrd.is_file():
        print(f"error: Expected a rerun recording, found no file '{rrd}'; record one with "
              "'gmmgp run SCAN --out DIR --rrd DIR/run.rrd'.", file=sys.stderr)
        return 2
    from rerun.experimental import ViewerClient

    client = ViewerClient.spawn(headless=True, port=args.port, hide_welcome_screen=True)
    try:
        client.open(str(rrd.resolve()))
        state = client.get_state()
        timelines = {t.name: t for r in state.recordings for t in r.timelines}
        if args.timeline not in timelines:
            print(f"error: Expected a timeline '{args.timeline}' in '{rrd}', found "
                  f"{sorted(timelines)}; pass --timeline.", file=sys.stderr)
            return 2
        t = timelines[args.timeline]
        client.set_time(args.timeline, sequence=t.end if args.time is None else args.time,
                        play_state="paused")
        time.sleep(args.wait)
        out = Path(args.png).resolve()
        out.parent.mkdir(parents=True, exist_ok=True)
        client.save_screenshot(str(out))
    finally:
        client.quit()
    print(f"wrote {args.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
