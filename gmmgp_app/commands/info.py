"""``gmmgp info``: summarise a scan (points, extent, spacing, units, classes)."""

from __future__ import annotations

import json

from .options import EXIT_OK, add_command, add_reader_options, read_scan_args

EXAMPLES = """examples:
  gmmgp info assets/demo_street.npz
  gmmgp info ../shared/data/kitti_odometry_seq00/velodyne/000000.bin
  gmmgp info ../shared/data/airborne/autzen_trim.laz --units ft"""


def add_parser(subparsers):
    p = add_command(subparsers, "info",
                    help="summarise a scan (points, extent, spacing, units, classes)",
                    epilog=EXAMPLES)
    p.add_argument("scan", nargs="+", help="scan file(s) or folder")
    add_reader_options(p)
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    return p


def run(args) -> int:
    from ..datasets import scan_summary

    scan = read_scan_args(args.scan, args)
    s = scan_summary(scan)
    if args.json:
        print(json.dumps(s, indent=2, default=float))
        return EXIT_OK
    ext = s["extent_m"]
    print(f"scan      {scan.source}")
    print(f"points    {s['n_points']:,}")
    print(f"extent    {ext[0]:.2f} x {ext[1]:.2f} x {ext[2]:.2f} m")
    print(f"bbox      min {_fmt3(s['bbox_min'])}  max {_fmt3(s['bbox_max'])}")
    print(f"spacing   {s['spacing_m']:.4f} m (median nearest neighbour)")
    print(f"units     {s['units']} (converted to metres)")
    off = s.get("offset")
    if off is not None and any(abs(v) > 0 for v in off):
        print(f"offset    {_fmt3(off)} (subtracted; outputs are shifted back)")
    print(f"origins   {'yes' if s['has_origins'] else 'no'}")
    if s.get("classes"):
        cls = ", ".join(f"{k}: {v:,}" for k, v in sorted(s["classes"].items(),
                                                          key=lambda kv: int(kv[0])))
        print(f"classes   {cls}")
    return EXIT_OK


def _fmt3(v) -> str:
    return "(" + ", ".join(f"{x:.3f}" for x in v) + ")"
