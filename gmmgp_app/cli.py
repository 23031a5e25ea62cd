"""The ``gmmgp`` command line.

Only this module turns exceptions into exit codes: bad input ends in one line
on stderr naming the problem and the fix, with exit code 2 and no traceback
(``--debug`` shows it). Exit code 130 after Ctrl-C.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

EXIT_OK, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 2, 130

_EXAMPLES = {
    "info": """examples:
  gmmgp info assets/demo_street.npz
  gmmgp info ../shared/data/kitti_odometry_seq00/velodyne/000000.bin
  gmmgp info ../shared/data/airborne/autzen_trim.laz --units ft""",
    "synth": """examples:
  gmmgp synth street --out out/street          # scan.npz + mesh.ply + scene.json
  gmmgp synth sphere --out out/sphere --seed 3
  gmmgp synth street --out out/big --density 4  # about 4x the points""",
    "run": """examples:
  gmmgp run assets/demo_street.npz --out out/demo
  gmmgp run scan.laz --out out/scan --set hgmm.split_threshold=0.02 --set gp.d_m=0.03
  gmmgp run scan.ply --out out/scan --method hgmm          # GMR-only baseline
  gmmgp run assets/demo_street.npz --out out/demo --stage hgmm   # print the HGMM levels
  gmmgp run scan.npz --out out/scan --config my.toml
  gmmgp run scan.laz --out out/scan --workers 2                 # GP blocks on a local Dask cluster
  gmmgp run scan.laz --out out/scan --scheduler tcp://HOST:8786 # ... or on an existing one
  gmmgp run city.laz --out out/city --tile-size 20 --workers 2  # 20 m tiles, stitched""",
    "view": """examples:
  gmmgp view assets/demo_street.npz
  gmmgp view out/demo/map
  gmmgp view out/demo --stage hgmm --level 2 --screenshot hgmm.png --size 1280x800
  xvfb-run -s "-screen 0 1600x1000x24" gmmgp view scan.ply     # on a machine without a display""",
    "eval": """examples:
  gmmgp eval out/demo --reference assets/demo_street_mesh.ply""",
    "sweep": """examples:
  gmmgp sweep assets/demo_street.npz --param hgmm.split_threshold --values 0.005,0.01,0.02""",
}


class _Parser(argparse.ArgumentParser):
    """argparse that exits with code 2 and a one-line message (it already does),
    keeping examples in the help text verbatim."""

    def __init__(self, *a, **kw):
        kw.setdefault("formatter_class", argparse.RawDescriptionHelpFormatter)
        super().__init__(*a, **kw)

    def error(self, message):
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _add_reader_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("reading the scan")
    g.add_argument("--units", help="input units when the file does not say, or to override "
                   "it: m, ft, us-ft, or a factor to metres")
    g.add_argument("--classes", help="keep only these label classes, e.g. 50,51 (KITTI)")
    g.add_argument("--poses", help="pose file (KITTI 3x4 rows) for a folder of scans")
    g.add_argument("--max-scans", type=int, help="use at most this many scans of a folder")


def reader_kwargs(args) -> dict:
    """read_scan options from the CLI's reader arguments (missing ones are skipped)."""
    kw = {}
    if getattr(args, "units", None):
        try:
            kw["units"] = float(args.units)
        except ValueError:
            kw["units"] = args.units
    if getattr(args, "classes", None):
        try:
            kw["classes"] = [int(c) for c in args.classes.split(",") if c.strip()]
        except ValueError:
            raise ValueError(f"Expected --classes as integers like 50,51, found "
                             f"{args.classes!r}.") from None
    if getattr(args, "poses", None):
        kw["poses"] = args.poses
    if getattr(args, "max_scans", None):
        kw["max_scans"] = args.max_scans
    return kw


def _add_config_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("configuration")
    g.add_argument("--config", help="TOML file with [prepare], [hgmm], [gmr], [gp], [surface]")
    g.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="override one field, e.g. --set hgmm.split_threshold=0.02 "
                        "(repeatable; see --help-config)")
    g.add_argument("--help-config", action="store_true",
                   help="list every config field with its default and meaning, then exit")


def _load_config(args):
    from .config import MappingConfig

    cfg = MappingConfig.from_toml(args.config) if args.config else MappingConfig()
    return cfg.with_overrides(args.set) if args.set else cfg


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="gmmgp",
        description="Uncertain implicit surface mapping from LiDAR scans: a hierarchical GMM "
                    "prior refined by local Gaussian processes, inspected stage by stage.",
        epilog="examples:\n  gmmgp info assets/demo_street.npz\n"
               "  gmmgp run assets/demo_street.npz --out out/demo\n"
               "  gmmgp synth street --out out/street\n\n"
               "Run 'gmmgp COMMAND --help' for each command's options and examples.",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    # The global flags are accepted after the command too ("gmmgp run ... -q").
    common = _Parser(add_help=False)
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help="show tracebacks on errors")
    common.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                        help="no progress output")

    def add(name, **kw):
        return sub.add_parser(name, parents=[common],
                              formatter_class=argparse.RawDescriptionHelpFormatter, **kw)

    p = add("info", help="summarise a scan (points, extent, spacing, units, classes)",
                       epilog=_EXAMPLES["info"])
    p.add_argument("scan", nargs="+", help="scan file(s) or folder")
    _add_reader_options(p)
    p.add_argument("--json", action="store_true", help="print JSON instead of text")

    p = add("synth", help="make a synthetic scene with exact ground truth",
                       epilog=_EXAMPLES["synth"])
    p.add_argument("name", help="scene: plane, sphere, box, street, street2")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--density", type=float, default=1.0, help="scan density multiplier")

    p = add("run", help="map a scan: prepare, HGMM, GMR, GP; save the map",
                       epilog=_EXAMPLES["run"])
    p.add_argument("scan", nargs="*", help="scan file(s) or folder")
    p.add_argument("--out", help="output folder (map/, summary.json, ...); required")
    p.add_argument("--method", default="gmmgp", choices=["gmmgp", "hgmm", "gpis"],
                   help="gmmgp (default, the paper's method), hgmm (GMR only), gpis")
    p.add_argument("--stage", default="all", choices=["prepare", "hgmm", "gmr", "all"],
                   help="stop after this stage (hgmm prints the level history)")
    p.add_argument("--rrd", help="record every stage to this rerun .rrd file (headless)")
    p.add_argument("--spawn", action="store_true", help="also open a rerun viewer")
    p.add_argument("--serve", action="store_true",
                   help="also serve the recording to viewers (bound to 127.0.0.1)")
    p.add_argument("--no-mesh", action="store_true", help="skip surface extraction")
    g = p.add_argument_group("large scans: map in tiles (DIR/map is then a tiled map)")
    g.add_argument("--tile-size", type=float, metavar="M",
                   help="map in square tiles of this edge (m) in x and y, each an independent "
                        "map, stitched smoothly; e.g. 20")
    g.add_argument("--tile-overlap", type=float, metavar="M",
                   help="with --tile-size: training margin and blending band around each "
                        "tile (m; default 2, at most half the tile size)")
    g.add_argument("--min-tile-points", type=int, metavar="N",
                   help="with --tile-size: a tile with fewer points joins its nearest mapped "
                        "tile (default 200)")
    g.add_argument("--no-stream", action="store_true",
                   help="with --tile-size: read a single LAS/LAZ file whole instead of "
                        "streaming it chunk by chunk into tiles on disk")
    g = p.add_argument_group("parallel execution of the GP blocks (of the tiles with "
                             "--tile-size)")
    g.add_argument("--workers", type=int, default=0,
                   help="start a local Dask cluster with N single-threaded workers")
    g.add_argument("--scheduler", help="use an existing Dask cluster, e.g. tcp://HOST:8786")
    g.add_argument("--processes", action="store_true",
                   help="with --workers: a local process pool instead of Dask")
    _add_reader_options(p)
    _add_config_options(p)

    from .viz.gui import add_view_arguments

    p = add("view", help="open the interactive desktop app", epilog=_EXAMPLES["view"])
    add_view_arguments(p)

    from .eval_cli import add_eval_arguments

    p = add("eval", help="compare gmmgp/hgmm/gpis/loggpis against a reference")
    add_eval_arguments(p)

    from .sweep import SWEEP_EXAMPLES, add_sweep_arguments

    p = add("sweep", help="map a scan for several values of one config field "
            "(one rerun recording, a 'sweep' timeline)", epilog=SWEEP_EXAMPLES)
    add_sweep_arguments(p)
    return parser


# --------------------------------------------------------------------------- commands
def cmd_info(args) -> int:
    from .datasets import read_scan, scan_summary

    scan = read_scan(args.scan[0] if len(args.scan) == 1 else args.scan, **reader_kwargs(args))
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


def cmd_synth(args) -> int:
    from .synth import write_scene

    paths = write_scene(args.name, args.out, seed=args.seed, density=args.density)
    for k, v in paths.items():
        print(f"{k:6s} {v}")
    return EXIT_OK


def cmd_run(args) -> int:
    if args.help_config:
        return _print_config_help()
    if not args.scan or not args.out:
        raise ValueError("Expected a scan and --out DIR, e.g. "
                         "'gmmgp run assets/demo_street.npz --out out/demo'.")
    cfg = _load_config(args)  # validate settings before the (slow) read
    spec = _tile_spec(args)

    from ._atomic import atomic_write_text
    from .datasets import read_scan
    from .pipeline import FanoutObserver, build_map
    from .progress import ConsoleObserver

    out = Path(args.out)
    _check_writable(out)
    console = ConsoleObserver(enabled=not args.quiet)
    observers = [console]
    recorder = None
    if args.rrd or args.spawn or args.serve:
        from .viz.rerun_observer import RerunObserver

        recorder = RerunObserver(args.rrd, spawn=args.spawn, serve=args.serve, config=cfg)
        observers.append(recorder)
    observer = FanoutObserver(*observers)
    t0 = time.perf_counter()
    stream, fallback = _stream_plan(args) if spec is not None else (None, None)
    if stream is not None:
        return _run_tiled(args, cfg, spec, None, out, console, t0, 0.0, stream=stream)
    scan = read_scan(args.scan[0] if len(args.scan) == 1 else args.scan, **reader_kwargs(args))
    read_s = time.perf_counter() - t0
    stop = None if args.stage == "all" else args.stage
    if stop is None and not args.no_mesh:  # refuse an impossible grid before fitting
        from .pipeline import surface_seeds
        from .stages.surface import check_grid_size

        check_grid_size(surface_seeds(scan, cfg), cfg.surface.voxel_size)
    if spec is not None:
        return _run_tiled(args, cfg, spec, scan, out, console, t0, read_s, fallback=fallback)
    from .distributed import open_executor

    with open_executor(workers=args.workers or None, scheduler=args.scheduler,
                       kind="processes" if args.processes else "dask") as executor:
        bar = _TaskBar(console, "GP blocks")
        smap = build_map(scan, cfg, method=args.method, observer=observer, stop_after=stop,
                         executor=executor, progress=bar)
        bar.close()
    smap.summary["seconds"] = {"read": read_s, **smap.summary["seconds"]}
    if args.stage == "hgmm" and smap.hgmm is not None:
        from .stages.hgmm import format_level_history

        print(format_level_history(smap.hgmm))
    try:
        out.mkdir(parents=True, exist_ok=True)
        smap.summary["scan"] = {"paths": [str(Path(s).resolve()) for s in args.scan],
                                "reader": reader_kwargs(args)}
        smap.save(out / "map")
        written = [out / "map"]
        if args.stage == "all" and not args.no_mesh:
            written += _write_meshes(smap, out, observer, console)
        if recorder is not None:
            recorder.close()  # writes the recording's footer now, not at interpreter exit
        atomic_write_text(out / "config.toml", cfg.to_toml())
        smap.summary["seconds"]["total"] = time.perf_counter() - t0
        atomic_write_text(out / "summary.json", json.dumps(_jsonable(smap.summary), indent=2))
        written += [out / "config.toml", out / "summary.json"]
    except OSError as exc:  # e.g. a full disk: numpy/zipfile do not name the file
        if exc.filename is None:
            exc.filename = str(out)
        raise
    if args.rrd:
        written.append(Path(args.rrd))
    if not args.quiet:
        print("wrote " + ", ".join(str(w) for w in written), file=sys.stderr)
    return EXIT_OK


def _tile_spec(args):
    """The TileSpec of ``run --tile-size`` (None without it), refusing the options a
    tiled run cannot honour before anything is read or written."""
    if args.tile_size is None:
        for flag, value in (("--tile-overlap", args.tile_overlap),
                            ("--min-tile-points", args.min_tile_points),
                            ("--no-stream", args.no_stream or None)):
            if value is not None:
                raise ValueError(f"{flag} only applies to tiled mapping, found it without "
                                 "--tile-size; add e.g. --tile-size 20.")
        return None
    if args.stage != "all":
        raise ValueError(f"--tile-size maps every stage of each tile, found --stage "
                         f"{args.stage}; drop --stage or --tile-size.")
    for flag, value in (("--rrd", args.rrd), ("--spawn", args.spawn),
                        ("--serve", args.serve)):
        if value:
            raise ValueError(f"{flag} records the stages of a single map, found it with "
                             f"--tile-size (tiles are mapped independently); drop {flag} or "
                             "--tile-size.")
    from .tiling import TileSpec

    kw = {"size": args.tile_size}
    # the default overlap shrinks with tiles smaller than 4 m instead of failing
    kw["overlap"] = (min(TileSpec.overlap, args.tile_size / 2) if args.tile_overlap is None
                     else args.tile_overlap)
    if args.min_tile_points is not None:
        kw["min_points"] = args.min_tile_points
    return TileSpec(**kw)


#: Points per chunk when streaming a LAS/LAZ file into tiles (one chunk in memory).
STREAM_CHUNK_POINTS = 1_000_000


def _stream_plan(args):
    """Whether ``run --tile-size`` streams its input: ``(plan, fallback)``.

    ``plan`` is None (read the scan whole) or a dict with the LAS/LAZ ``path``, the
    local ``offset`` and whether the file has ``origins`` (extra dimensions
    ``origin_x/y/z``). ``fallback`` says why a single LAS/LAZ file is read whole
    (None when it streams, or when the input is not a single LAS/LAZ file: only the
    in-memory readers know other formats and folders).

    Streaming (:func:`gmmgp_app.tiling.build_tiled_map_from_las`) reads the stored
    coordinates as they are, every point of the file. So it is used only when that
    is exactly what :func:`gmmgp_app.datasets.read_scan` would return: no class
    filter, no pose file, no scan selection, and coordinates already in metres (the
    ``--units`` override or the file's CRS unit has a factor of 1). Anything else
    falls back to the in-memory reader with a one-line notice instead of being
    re-implemented here: applying a class filter or a unit factor while streaming
    would need the tiling module to transform each chunk, and mapping feet as metres
    would silently scale every length parameter of the config by 3.3. Options the
    reader refuses for a single file (``--max-scans``, a CRS in degrees) also fall
    back, silently, so that the reader's own error and fix are what the user sees.
    """
    if len(args.scan) != 1:
        return None, None
    path = Path(args.scan[0])
    if path.suffix.lower() not in (".las", ".laz") or path.is_dir():
        return None, None
    import laspy

    from .datasets._common import OFFSET_THRESHOLD_M, auto_offset, check_file, parse_units
    from .datasets.las import _check_declared_size, crs_units, vlr_crs_present

    kw = reader_kwargs(args)
    check_file(path)
    _check_declared_size(path)  # a corrupt header fails here, before any work
    try:
        with laspy.open(str(path)) as reader:
            hdr = reader.header
            has_org = {"origin_x", "origin_y", "origin_z"} <= set(
                hdr.point_format.dimension_names)
            lo = np.asarray(hdr.mins, dtype=np.float64)
            hi = np.asarray(hdr.maxs, dtype=np.float64)
            horiz, vert, _ = crs_units(hdr)
            crs = vlr_crs_present(hdr)
    except (laspy.errors.LaspyException, ValueError, OSError):
        return None, "unreadable header"  # the in-memory reader reports it with the fix
    why, notice = None, True
    if args.no_stream:
        why, notice = "--no-stream", False
    elif "classes" in kw or "poses" in kw:
        why = f"{'--classes' if 'classes' in kw else '--poses'} is applied by the in-memory " \
              "reader only"
    elif "max_scans" in kw:
        return None, "--max-scans"
    elif "units" in kw:
        if parse_units(kw["units"])[1] != 1.0:
            why = f"--units {args.units} scales the coordinates, which streaming does not do"
    elif horiz == "degrees":
        return None, "CRS in degrees"
    elif any(u is not None and float(u) != 1.0 for u in (horiz, vert)):
        why = "the file's CRS unit is not the metre and streaming does not scale coordinates"
    if why is not None:
        if notice:
            print(f"gmmgp run: notice: {why}, so '{path}' is read whole instead of streamed "
                  "into tiles (memory ~ the whole scan).", file=sys.stderr)
        return None, why
    if horiz is None and crs and "units" not in kw:  # as the reader warns
        warnings.warn(f"Could not find a linear unit in the CRS of '{path}'; assuming "
                      "metres. Pass --units ft or --units us-ft if that is wrong.")
    # The offset the reader would choose (datasets finalize, offset="auto": a LAS holds
    # no local offset of its own), so that a streamed map and an in-memory one share
    # their local frame and hence their tile boundaries. The header's bounds stand in
    # for the points' (the same for files written by laspy, PDAL or LAStools; should a
    # header lie, the map is still consistent, only its tile grid is shifted).
    far = max(np.abs(lo).max(), np.abs(hi).max()) > OFFSET_THRESHOLD_M
    offset = auto_offset(lo) if far else np.zeros(3)
    return {"path": path, "offset": offset, "origins": has_org}, None


def _run_tiled(args, cfg, spec, scan, out: Path, console, t0: float, read_s: float, *,
               stream=None, fallback=None) -> int:
    """``run --tile-size``: map tile by tile, save the tiled map, mesh the stitched field.

    With ``stream`` (:func:`_stream_plan`; ``scan`` is then None) the LAS/LAZ file is
    streamed into per-tile pieces under a temporary folder inside ``out`` (the same
    file system as the output, which must hold the map anyway, unlike a possibly
    small /tmp); the folder is removed once the map is saved to ``out/map`` (the save
    copies the tiles), also on errors and Ctrl-C, and the mesh is extracted from the
    saved map, which is what later commands open.
    """
    import dataclasses
    import shutil
    import tempfile

    from ._atomic import atomic_write_text
    from .distributed import open_executor
    from .stages.surface import write_mesh_ply
    from .tiling import build_tiled_map, load_tiled_map

    created = not out.exists()
    work = None
    ok = False
    try:
        t1 = time.perf_counter()
        with open_executor(workers=args.workers or None, scheduler=args.scheduler,
                           kind="processes" if args.processes else "dask") as executor:
            bar = _TaskBar(console, "tiles")
            if stream is None:
                tmap = build_tiled_map(scan, cfg, spec, method=args.method, executor=executor,
                                       progress=bar, keep_points=True)
            else:
                out.mkdir(parents=True, exist_ok=True)
                work = Path(tempfile.mkdtemp(prefix=".stream-", dir=out))
                tmap = _stream_tiles(stream, cfg, spec, args.method, work, executor, bar)
            bar.close()
        seconds = {"read": read_s, "tiles": time.perf_counter() - t1}
        # per tile: a streamed map loads each tile from its work folder, a few at a time
        per_tile = [sum(t.summary.get("seconds", {}).values()) for _, t in tmap.tiles.items()]
        summary = {"method": args.method, "tiled": True, "tile_spec": dataclasses.asdict(spec),
                   **tmap.summary, "n_absorbed_tiles": len(tmap.owners),
                   "n_skipped_tiles": len(tmap.summary.get("skipped_tiles", {})),
                   "tile_seconds": {"median": float(np.median(per_tile)),
                                    "max": float(np.max(per_tile)),
                                    "sum": float(np.sum(per_tile))},
                   "scan": {"paths": [str(Path(s).resolve()) for s in args.scan],
                            "reader": reader_kwargs(args)},
                   "streamed": stream is not None,
                   "stream": (None if stream is None else
                              {"chunk_points": STREAM_CHUNK_POINTS,
                               "origins": bool(stream["origins"])}),
                   "stream_fallback": fallback,
                   "seconds": seconds, "counts": {}}
        tmap.summary = summary
        out.mkdir(parents=True, exist_ok=True)
        t2 = time.perf_counter()
        tmap.save(out / "map")
        seconds["save"] = time.perf_counter() - t2
        if work is not None:
            shutil.rmtree(work)
            work = None
            # from here on the map is the saved one: nothing may point into the work folder
            tmap = load_tiled_map(out / "map", load_points=False)
        written = [out / "map"]
        if not args.no_mesh:
            t3 = time.perf_counter()
            mesh = tmap.extract_surface(progress=console.progress)
            seconds["surface"] = time.perf_counter() - t3
            summary["counts"]["surface"] = {args.method: {"vertices": len(mesh.vertices),
                                                          "faces": len(mesh.faces)}}
            written.append(write_mesh_ply(mesh, out / f"mesh_{args.method}.ply",
                                          offset=tmap.offset, vmax=_std_colour_max([mesh])))
        atomic_write_text(out / "config.toml", cfg.to_toml())
        seconds["total"] = time.perf_counter() - t0
        atomic_write_text(out / "summary.json", json.dumps(_jsonable(summary), indent=2))
        written += [out / "config.toml", out / "summary.json"]
        ok = True
    except OSError as exc:  # e.g. a full disk: numpy/zipfile do not name the file
        if exc.filename is None:
            exc.filename = str(out)
        raise
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
        if not ok and created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()  # a failed streamed run leaves no empty output folder behind
    if not args.quiet:
        how = "streamed, " if stream is not None else ""
        print(f"mapped {summary['n_tiles']} tiles ({how}{len(tmap.owners)} small ones joined "
              f"a neighbour, {summary['n_skipped_tiles']} skipped)", file=sys.stderr)
        print("wrote " + ", ".join(str(w) for w in written), file=sys.stderr)
    return EXIT_OK


def _stream_tiles(stream, cfg, spec, method, work: Path, executor, progress):
    """:func:`build_tiled_map_from_las` of a :func:`_stream_plan`, with laspy's and
    lazrs's errors on a file whose points are corrupt turned into a ScanReadError."""
    import laspy

    from .datasets import ScanReadError
    from .tiling import build_tiled_map_from_las

    errors = (laspy.errors.LaspyException,)
    try:
        import lazrs

        errors += (lazrs.LazrsError,)
    except ImportError:  # no LAZ backend: laspy raises a LaspyException saying so
        pass
    try:
        return build_tiled_map_from_las(stream["path"], cfg, spec, method, work_dir=work,
                                        executor=executor, chunk_size=STREAM_CHUNK_POINTS,
                                        progress=progress, offset=stream["offset"])
    except errors as exc:
        raise ScanReadError(f"Cannot stream '{stream['path']}' as LAS/LAZ ({type(exc).__name__}:"
                            f" {exc}); the file is corrupt or truncated, export or download it "
                            "again.") from None


def _std_colour_max(meshes) -> float | None:
    """Top of the std colour scale shared by ``meshes``: the largest 98th percentile of
    their vertex standard deviations (None when they have no vertex)."""
    return max((float(np.sqrt(np.quantile(m.vertex_variance, 0.98)))
                for m in meshes if len(m.vertices)), default=None)


def _write_meshes(smap, out: Path, observer, console) -> list:
    """Marching-cubes surfaces of the map and of its HGMM prior (GMR alone)."""
    from .pipeline import StagePayload
    from .stages.surface import extract_surface, write_mesh_ply

    t0 = time.perf_counter()
    sc = smap.config.surface
    meshes = {}
    if smap.method != "hgmm":
        meshes[smap.method] = smap.extract_surface(progress=console.progress)
    if smap.hgmm is not None:
        meshes["hgmm"] = extract_surface(smap.prior.predict, smap.seed_points,
                                         voxel_size=sc.voxel_size, max_std=sc.max_std,
                                         progress=console.progress)
    seconds = time.perf_counter() - t0
    smap.summary["seconds"]["surface"] = seconds
    smap.summary["counts"]["surface"] = {k: {"vertices": len(m.vertices), "faces": len(m.faces)}
                                         for k, m in meshes.items()}
    observer.on_stage("surface", StagePayload(meshes, seconds))
    # Same colour scale for every mesh so they can be compared side by side.
    vmax = _std_colour_max(meshes.values())
    return [write_mesh_ply(m, out / f"mesh_{k}.ply", offset=smap.offset, vmax=vmax)
            for k, m in meshes.items()]


def _print_config_help() -> int:
    from .config import MappingConfig

    for name, default, doc in MappingConfig.describe():
        print(f"{name:32s} {default!s:>10s}  {doc}")
    return EXIT_OK


def cmd_sweep(args) -> int:
    from .sweep import cmd_sweep as run

    return run(args)


def cmd_eval(args) -> int:
    from .eval_cli import cmd_eval as run

    return run(args)


def cmd_view(args) -> int:
    from .viz.gui import cmd_view as run

    return run(args)


class _TaskBar:
    """``progress(done, total)`` callback drawing one bar, created on first use."""

    def __init__(self, console, desc):
        self.console, self.desc, self.bar = console, desc, None

    def __call__(self, done, total):
        if self.bar is None:
            self.bar = self.console.progress(total, self.desc)
        self.bar.update(done - self.bar.n)

    def close(self):
        if self.bar is not None:
            self.bar.close()


def _check_writable(out: Path) -> None:
    probe = out
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise PermissionError(f"Cannot write to output folder '{out}' ('{probe}' is not a "
                              "writable folder); choose another --out.")


def _jsonable(obj):
    from .pipeline import _jsonable as j

    return j(obj)


# --------------------------------------------------------------------------- entry point
_COMMANDS = {"info": cmd_info, "synth": cmd_synth, "run": cmd_run,
             "view": cmd_view, "eval": cmd_eval, "sweep": cmd_sweep}


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return EXIT_BAD_INPUT
    # One line per warning, like errors (a recording test harness still sees them).
    previous = warnings.formatwarning
    if not args.debug:
        warnings.formatwarning = lambda msg, *a, **k: \
            f"gmmgp {args.command}: warning: {_one_line(msg)}\n"
    try:
        return _run_command(args)
    finally:
        warnings.formatwarning = previous


def _run_command(args) -> int:
    try:
        return _COMMANDS[args.command](args)
    except BrokenPipeError:  # e.g. "gmmgp info ... | head": the reader left, not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    except KeyboardInterrupt:
        print("gmmgp: interrupted; nothing half-written was left behind.", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (ValueError, OSError, NotImplementedError, KeyError, MemoryError) as exc:
        if args.debug:
            raise
        print(f"gmmgp {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:  # a bug, not bad input: still one line, with a hint
        if args.debug:
            raise
        print(f"gmmgp {args.command}: internal error: {type(exc).__name__}: {_one_line(exc)} "
              "(rerun with --debug for the traceback and report it)", file=sys.stderr)
        return 1


def _one_line(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror and exc.filename:
        msg = f"{exc.strerror}: '{exc.filename}'"
        if exc.errno == 28:
            msg += "; free some disk space or choose another --out"
        return msg
    text = str(exc) or type(exc).__name__
    return " ".join(text.split())


if __name__ == "__main__":
    sys.exit(main())
