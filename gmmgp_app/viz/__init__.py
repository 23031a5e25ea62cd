"""The viewers: the desktop app (``gui*``, Open3D), the rerun recorder and the check's
recording. This package itself is light (no Open3D, rerun or app module is imported
here): the command line's parser reads the app's options (:func:`add_view_arguments`)
and :data:`STAGES` from it without importing the app.
"""

import argparse

#: Stages the app shows, in pipeline order; "surface" is marching cubes on the final field.
STAGES = ("scan", "prepare", "hgmm", "gmr", "gp", "surface")


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
