"""``gmmgp sweep``: map a scan for several values of one config field (one rerun
recording, a 'sweep' timeline; :mod:`gmmgp_app.sweep` holds the sweep itself)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .options import (EXIT_OK, METHODS, add_command, add_config_options, add_reader_options,
                      add_voxel_option, load_config, print_config_help, read_scan_args)

EXAMPLES = """examples:
  gmmgp sweep assets/demo_street.npz --param hgmm.split_threshold \\
        --values 0.005,0.01,0.02,0.04 --rrd out/sweep/sweep.rrd
  gmmgp sweep assets/demo_street.npz --param gp.d_m --values 0.01,0.02,0.05 \\
        --reference assets/demo_street_mesh.ply --out out/sweep_dm
  gmmgp sweep scan.npz --param hgmm.n_children --values 4,8 --no-mesh --out out/children"""


def add_parser(subparsers):
    p = add_command(subparsers, "sweep", help="map a scan for several values of one config "
                    "field (one rerun recording, a 'sweep' timeline)", epilog=EXAMPLES)
    return add_sweep_arguments(p)


def add_sweep_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``gmmgp sweep`` arguments to ``parser``."""
    parser.add_argument("scan", nargs="+", help="scan file(s) or folder")
    parser.add_argument("--param", required=True, metavar="SECTION.FIELD",
                        help="config field to sweep, e.g. hgmm.split_threshold "
                             "(any field of 'gmmgp run --help-config')")
    parser.add_argument("--values", required=True, metavar="V1,V2,...",
                        help="comma separated values, e.g. 0.005,0.01,0.02,0.04")
    parser.add_argument("--rrd", help="record every value to this rerun .rrd file, one step "
                                      "per value on the 'sweep' timeline")
    parser.add_argument("--out", help="folder for sweep.json (default: beside --rrd, else .)")
    parser.add_argument("--reference", help="reference mesh or dense cloud (original frame): "
                                            "adds rmse_sdf and surface_rmse per value")
    parser.add_argument("--method", default="gmmgp", choices=METHODS)
    parser.add_argument("--no-mesh", action="store_true", help="skip surface extraction")
    add_voxel_option(parser, "default: surface.voxel_size, 0.05")
    add_reader_options(parser)
    add_config_options(parser)
    if parser.epilog is None:
        parser.epilog = EXAMPLES
    return parser


def run(args) -> int:
    """Run ``gmmgp sweep``; returns the exit code (0)."""
    from .._atomic import atomic_write_text
    from ..evaluation import Reference
    from ..progress import ConsoleObserver
    from ..sweep import parse_values, run_sweep, table_markdown

    if args.help_config:
        return print_config_help()
    cfg = load_config(args, voxel=True)
    values = parse_values(args.param, args.values, cfg)
    if args.out:
        out = Path(args.out)
    elif args.rrd:
        out = Path(args.rrd).resolve().parent
    else:
        out = Path(".")
    reference = Reference.load(args.reference) if args.reference else None
    scan = read_scan_args(args.scan, args)
    quiet = getattr(args, "quiet", False)
    console = ConsoleObserver(enabled=not quiet)
    mesh = not args.no_mesh and args.method != "loggpis"  # loggpis has no zero level set
    rows = run_sweep(scan, args.param, values, base=cfg, method=args.method, rrd=args.rrd,
                     reference=reference, mesh=mesh, console=console)
    out.mkdir(parents=True, exist_ok=True)
    result = {"param": args.param, "values": [r["value"] for r in rows],
              "scan": str(scan.source), "method": args.method,
              "reference": args.reference, "rrd": args.rrd, "rows": rows}
    path = atomic_write_text(out / "sweep.json", json.dumps(result, indent=2, default=float))
    print(table_markdown(args.param, rows), end="")
    if not quiet:
        print(f"wrote {path}" + (f", {args.rrd}" if args.rrd else ""), file=sys.stderr)
    return EXIT_OK
