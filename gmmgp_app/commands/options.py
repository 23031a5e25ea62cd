"""Options shared by the commands (the leaf of the command tree: no command imports
another): registering a command, reader options and their ``read_scan`` keywords,
configuration options and loading, the surface voxel, the method list."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from ..config import METHODS

__all__ = ["EXIT_OK", "EXIT_BAD_INPUT", "EXIT_INTERRUPTED", "METHODS", "Parser", "add_command",
           "add_reader_options", "reader_kwargs", "read_scan_args", "add_config_options",
           "load_config", "print_config_help", "add_voxel_option"]

EXIT_OK, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 2, 130


class Parser(argparse.ArgumentParser):
    """argparse that exits with code 2 and a one-line message (it already does),
    keeping examples in the help text verbatim."""

    def __init__(self, *a, **kw):
        kw.setdefault("formatter_class", argparse.RawDescriptionHelpFormatter)
        super().__init__(*a, **kw)

    def error(self, message):
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _global_flags() -> argparse.ArgumentParser:
    # The global flags are accepted after the command too ("gmmgp run ... -q").
    common = Parser(add_help=False)
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help="show tracebacks on errors")
    common.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                        help="no progress output")
    return common


def add_command(subparsers, name: str, **kw) -> argparse.ArgumentParser:
    """A command's sub-parser, with the global flags and verbatim examples."""
    return subparsers.add_parser(name, parents=[_global_flags()],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, **kw)


# --------------------------------------------------------------------------- reading
def add_reader_options(p: argparse.ArgumentParser, classes: bool = True) -> None:
    """``--units``, ``--classes``, ``--poses``, ``--max-scans`` (see :func:`reader_kwargs`)."""
    g = p.add_argument_group("reading the scan")
    g.add_argument("--units", help="input units when the file does not say, or to override "
                   "it: m, ft, us-ft, or a factor to metres")
    if classes:
        g.add_argument("--classes", help="keep only these label classes, e.g. 50,51 (KITTI)")
    g.add_argument("--poses", help="pose file (KITTI 3x4 rows) for a folder of scans")
    g.add_argument("--max-scans", type=int, help="use at most this many scans of a folder")


def reader_kwargs(args) -> dict:
    """read_scan options from the reader arguments (missing ones are skipped)."""
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


def read_scan_args(paths, args):
    """``read_scan`` of one path or several, with the reader options of ``args``."""
    from ..datasets import read_scan

    return read_scan(paths[0] if len(paths) == 1 else list(paths), **reader_kwargs(args))


# --------------------------------------------------------------------------- config
def add_config_options(p: argparse.ArgumentParser) -> None:
    """``--config``, ``--set`` and ``--help-config`` (see :func:`load_config`)."""
    g = p.add_argument_group("configuration")
    g.add_argument("--config", help="TOML file with [prepare], [hgmm], [gmr], [gp], [surface]")
    g.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="override one field, e.g. --set hgmm.split_threshold=0.02 "
                        "(repeatable; see --help-config)")
    g.add_argument("--help-config", action="store_true",
                   help="list every config field with its default and meaning, then exit")


def add_voxel_option(p: argparse.ArgumentParser, default_help: str) -> None:
    """``--voxel-size M``: the surface voxel, one spelling on every command (the same
    field as ``--set surface.voxel_size=M``)."""
    p.add_argument("--voxel-size", type=float, default=None, metavar="M",
                   help=f"marching-cubes voxel of the surface in metres ({default_help})")


def load_config(args, voxel: bool = False):
    """The MappingConfig of ``--config`` and ``--set``; with ``voxel``, ``--voxel-size``
    (when given) sets ``surface.voxel_size`` on top."""
    from ..config import MappingConfig

    cfg = MappingConfig.from_toml(args.config) if getattr(args, "config", None) \
        else MappingConfig()
    if getattr(args, "set", None):
        cfg = cfg.with_overrides(args.set)
    if voxel and getattr(args, "voxel_size", None) is not None:
        cfg = cfg.replace("surface.voxel_size", args.voxel_size)
    return cfg


def print_config_help() -> int:
    """Print every config field with its default and meaning."""
    from ..config import MappingConfig

    for name, default, doc in MappingConfig.describe():
        print(f"{name:32s} {default!s:>10s}  {doc}")
    return EXIT_OK


# --------------------------------------------------------------------------- output
def check_writable(target, flag: str = "--out", what: str = "output folder ") -> None:
    """Refuse, before any work, an output path whose nearest existing ancestor is not a
    writable folder (``what`` names the target in the one-line error, ``flag`` the fix)."""
    target = Path(target)
    probe = target
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise PermissionError(f"Cannot write to {what}'{target}' ('{probe}' is not a "
                              f"writable folder); choose another {flag}.")
