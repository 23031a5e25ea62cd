"""``gmmgp view``: the interactive desktop app (:mod:`gmmgp_app.viz.gui`).

The app's modules are imported when the command runs, not when the command line's
parser is built: its options come from the light :mod:`gmmgp_app.viz` package.
"""

from __future__ import annotations

from ..viz import add_view_arguments
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
