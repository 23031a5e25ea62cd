"""``gmmgp view``: the interactive desktop app (:mod:`gmmgp_app.viz.gui`).

The app's modules are imported when the command runs, not when the command line's
parser is built (they cost every ``gmmgp`` start 0.08 CPU-s): its options are here.
"""

from __future__ import annotations

import argparse

from ..viz import STAGES
from .options import add_command, add_config_options, load_config

EXAMPLES = """examples:
  gmmgp view assets/demo_street.npz
  gmmgp view out/demo/map
  gmmgp view out/demo                      # a run folder: map, its mesh and summary
  gmmgp view out/city                      # a tiled run: tiles loaded around the view
  gmmgp view out/check                     # a 'gmmgp check' result: points by z, segments
  gmmgp view out/demo --stage hgmm --level 2 --screenshot hgmm2.png --size 1280x800
  gmmgp view scan.npz --stage hgmm --compare hgmm.split_threshold=0.03 --screenshot cmp.png
  gmmgp view out/check --segment 1 --screenshot seg1.png
  gmmgp view ../shared/data/stanford_bunny/raw_scans   # a folder of scans, as 'gmmgp run' reads it
  xvfb-run -s "-screen 0 1600x1000x24" gmmgp view scan.ply     # on a machine without a display"""


def add_view_arguments(parser) -> None:
    """The app's options (``gmmgp view`` adds the shared configuration options)."""
    parser.add_argument("target", help="scan file, saved map folder (map/), a 'gmmgp run' "
                        "output folder (single or tiled map) or a 'gmmgp check' output "
                        "folder")
    parser.add_argument("--voxel-size", type=float, default=0.1, metavar="M",
                        help="marching-cubes voxel of the surface in metres (default 0.1; "
                             "the map's 0.05 is sharper but about 4x slower)")
    parser.add_argument("--size", default="1600x1000", metavar="WxH",
                        help="window size in pixels (default 1600x1000)")
    parser.add_argument("--stage", default=None, choices=STAGES,
                        help="stage shown first (default: the last one computed)")
    parser.add_argument("--screenshot", metavar="PNG",
                        help="render the stage once to this PNG and exit, no window (default "
                             "stage: the last; a scan is mapped first)")
    parser.add_argument("--level", type=int, default=0,
                        help="HGMM level of the ellipsoids shown (with --stage hgmm)")
    parser.add_argument("--compare", action="append", default=[], metavar="KEY=VALUE",
                        help="with --screenshot: map again with this setting (repeatable, "
                             "e.g. hgmm.split_threshold=0.03) and draw the first run beside "
                             "the second")
    parser.add_argument("--segment", type=int, default=None, metavar="N",
                        help="with --screenshot of a check result: frame change segment N "
                             "(1 = the largest), drawn red")
    parser.add_argument("--script", metavar="JSON",
                        help="run these steps after the first computation (automation and "
                             "screenshots; see gmmgp_app.viz.gui_script)")
    parser.add_argument("--no-3d", action="store_true", help=argparse.SUPPRESS)  # tests


def add_parser(subparsers):
    p = add_command(subparsers, "view", help="open the interactive desktop app",
                    epilog=EXAMPLES)
    add_view_arguments(p)
    add_config_options(p)
    return p


def run(args) -> int:
    from ..viz.gui import open_view

    if args.help_config:
        from .options import print_config_help

        return print_config_help()
    return open_view(args, load_config(args))
