#!/usr/bin/env python
"""Render a rerun recording (.rrd) to a PNG without a display.

``rerun FILE.rrd --headless --screenshot-to out.png`` takes its screenshot as soon
as the window exists, often before a large recording (meshes of a few 100k
vertices) has loaded: the views come out empty. This is a command line for
:func:`gmmgp_app.viz.rerun_observer.screenshot`, which waits until the headless
viewer has loaded everything, moves the time cursor (default: the end of the
``stage`` timeline, so every stage is shown) and saves the whole window.

Needs a Vulkan device or Mesa's llvmpipe (installed by scripts/setup.sh).

Examples
--------
    python scripts/render_rrd.py out/demo/demo.rrd docs/rerun_demo.png
    python scripts/render_rrd.py out/demo/demo.rrd /tmp/level1.png --timeline level --time 1
"""

from __future__ import annotations

import argparse
import sys


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("rrd", help="recording to render")
    ap.add_argument("png", help="output PNG (whole viewer window)")
    ap.add_argument("--timeline", default="stage", help="timeline to move (default: stage)")
    ap.add_argument("--time", type=int, help="sequence value (default: the timeline's end)")
    ap.add_argument("--size", default="1600x900", help="window size in points (1600x900)")
    ap.add_argument("--settle", type=float, default=3.0,
                    help="seconds to let the views draw after loading (default 3)")
    args = ap.parse_args(argv)
    from gmmgp_app.viz.rerun_observer import RerunError, screenshot

    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        print(f"error: Expected --size as WIDTHxHEIGHT, found '{args.size}'; use e.g. "
              "1600x900.", file=sys.stderr)
        return 2
    try:
        png = screenshot(args.rrd, args.png, window_size=(w, h), settle=args.settle,
                         timeline=args.timeline, sequence=args.time)
    except (FileNotFoundError, RerunError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
