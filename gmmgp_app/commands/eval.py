"""``gmmgp eval``: compare gmmgp/hgmm/gpis/loggpis against a reference
(:mod:`gmmgp_app.compare` holds the comparison itself)."""

from __future__ import annotations

import sys
from pathlib import Path

from .options import (EXIT_OK, add_command, add_reader_options, add_voxel_option,
                      reader_kwargs)

EXAMPLES = """examples:
  gmmgp run assets/demo_street.npz --out out/demo
  gmmgp eval out/demo --scan assets/demo_street.npz --reference assets/demo_street_mesh.ply
  gmmgp eval out/demo --scan assets/demo_street.npz --reference ref.ply --methods gmmgp,gpis,loggpis
  gmmgp eval out/kitti --scan ../shared/data/kitti_odometry_seq00/velodyne/000000.bin \\
      --reference ../shared/data/kitti_odometry_seq00/velodyne \\
      --reference-poses ../shared/data/kitti_odometry_seq00/poses_gicp_estimated.txt"""


def add_parser(subparsers):
    p = add_command(subparsers, "eval", help="compare gmmgp/hgmm/gpis/loggpis against a "
                    "reference", epilog=EXAMPLES)
    add_eval_arguments(p)
    return p


def add_eval_arguments(p) -> None:
    """Add the ``eval`` arguments to an argparse (sub-)parser."""
    p.add_argument("directory", help="output folder of 'gmmgp run' (holds map/)")
    p.add_argument("--reference", required=True,
                   help="reference surface: a mesh (.ply/.obj/.stl/.off; exact distance) or a "
                        "dense point cloud / folder of scans (nearest-neighbour distance)")
    p.add_argument("--methods", default=None,
                   help="comma-separated subset of gmmgp,hgmm,gpis,loggpis "
                        "(default: all four)")
    p.add_argument("--scan", nargs="+",
                   help="the scan the map was built from (default: the paths recorded in "
                        "the map, when there are any)")
    p.add_argument("--out", help="output folder (default: DIRECTORY/eval)")
    p.add_argument("--queries", type=int, default=20000,
                   help="number of test points (default 20000)")
    p.add_argument("--bins", default=None,
                   help="distance bin edges in metres, e.g. 0,0.05,0.1,0.2,0.3,0.5 "
                        "(the default, the paper's range)")
    p.add_argument("--lambda", dest="lam", type=float, default=None,
                   help="Log-GPIS lambda in 1/m (default sqrt(3) / gp.length_scale)")
    add_voxel_option(p, "of extracted surfaces; default: the map's surface.voxel_size")
    p.add_argument("--no-surface", action="store_true",
                   help="skip the Chamfer / Hausdorff distances of the surfaces")
    p.add_argument("--reference-poses",
                   help="pose file for a folder of reference scans (KITTI 3x4 rows)")
    p.add_argument("--reference-skip", type=int, default=None,
                   help="drop the first N scans of a reference folder (e.g. 1 when scan 0 "
                        "is the training scan)")
    p.add_argument("--seed", type=int, default=0, help="seed of the query sampling")
    add_reader_options(p, classes=False)


def run(args) -> int:
    """Run ``gmmgp eval`` from parsed arguments; returns the exit code (0)."""
    quiet = getattr(args, "quiet", False)
    log = (lambda *a: None) if quiet else (lambda *a: print(*a, file=sys.stderr, flush=True))
    directory = Path(args.directory)
    from ..compare import (EvalInputError, check_tiled_methods, is_tiled, load_reference,
                           parse_bins, parse_methods, run_evaluation, tiled_methods,
                           write_outputs)

    methods = parse_methods(args.methods)
    bins = parse_bins(args.bins)
    if args.queries < 10:
        raise EvalInputError(f"Expected --queries >= 10, found {args.queries}.")
    out = Path(args.out) if args.out else directory / "eval"

    from ..datasets import read_scan
    from ..tiling import load_any_map

    smap = load_any_map(directory)
    if is_tiled(smap):
        provided = tiled_methods(smap)
        if args.methods is None:  # the default: what the tiled map can answer for
            methods = provided
            log(f"tiled map: evaluating {','.join(provided)} (the other methods need an "
                "untiled run)")
        check_tiled_methods(methods, provided)
    scan_paths = args.scan or smap.summary.get("scan", {}).get("paths")
    if not scan_paths:
        raise EvalInputError(
            f"The map in '{directory}' does not record its scan; pass it with --scan "
            "(the same file(s) given to 'gmmgp run').")
    scan_kw = reader_kwargs(args) or dict(smap.summary.get("scan", {}).get("reader", {}))
    log(f"reading scan {', '.join(map(str, scan_paths))}")
    scan = read_scan(scan_paths[0] if len(scan_paths) == 1 else list(scan_paths), **scan_kw)
    n_saved = smap.summary.get("n_points" if is_tiled(smap) else "n_scan_points")
    if n_saved is not None and int(n_saved) != len(scan):
        raise EvalInputError(
            f"The scan has {len(scan)} points but the map was built from {n_saved}; pass the "
            "scan (and reader options) used with 'gmmgp run'.")
    log(f"reading reference {args.reference}")
    ref_kw = {}
    if args.reference_poses:
        ref_kw["poses"] = args.reference_poses
    reference = load_reference(args.reference, ref_kw, args.reference_skip)
    results = run_evaluation(scan, smap, reference, methods, bins=bins,
                             n_queries=args.queries, seed=args.seed, lam=args.lam,
                             surfaces=not args.no_surface, voxel_size=args.voxel_size,
                             run_dir=directory, log=log)
    results["scan"] = [str(p) for p in scan_paths]
    written = write_outputs(results, out)
    log("wrote " + ", ".join(str(w) for w in written))
    return EXIT_OK


