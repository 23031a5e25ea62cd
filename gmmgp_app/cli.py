"""The ``gmmgp`` command line: dispatch to one module per command.

Each command is a module of :mod:`gmmgp_app.commands` with ``add_parser(subparsers)``
and ``run(args) -> int``; a new command is one line in :data:`COMMANDS`. Only this
module turns exceptions into exit codes: bad input ends in one line on stderr
naming the problem and the fix, with exit code 2 and no traceback (``--debug``
shows it). Exit code 130 after Ctrl-C.
"""

from __future__ import annotations

import os
import sys
import warnings
from importlib import import_module

from .commands.options import EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_OK, Parser

#: The commands, in the order ``gmmgp --help`` lists them (modules of gmmgp_app.commands).
COMMANDS = ["info", "synth", "run", "view", "eval", "sweep", "check"]


def _command(name: str):
    return import_module(f"gmmgp_app.commands.{name}")


def build_parser() -> Parser:
    parser = Parser(
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
    for name in COMMANDS:
        _command(name).add_parser(sub)
    return parser


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
        return _command(args.command).run(args)
    except BrokenPipeError:  # e.g. "gmmgp info ... | head": the reader left, not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    except KeyboardInterrupt:
        return _interrupted()
    except (ValueError, OSError, NotImplementedError, KeyError, MemoryError) as exc:
        if args.debug:
            raise
        print(f"gmmgp {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:  # a bug, not bad input: still one line, with a hint
        if _from_interrupt(exc):
            return _interrupted()
        if args.debug:
            raise
        print(f"gmmgp {args.command}: internal error: {type(exc).__name__}: {_one_line(exc)} "
              "(rerun with --debug for the traceback and report it)", file=sys.stderr)
        return 1


def _interrupted() -> int:
    """The one line and exit code of a run the user interrupted (Ctrl-C)."""
    print("gmmgp: interrupted; nothing half-written was left behind.", file=sys.stderr)
    return EXIT_INTERRUPTED


def _from_interrupt(exc: BaseException) -> bool:
    """Whether ``exc`` is a Ctrl-C in disguise: a KeyboardInterrupt that arrived while a
    compiled (numba) call was returning, which CPython reports as ``SystemError: ...
    returned a result with an exception set`` with the interrupt as its cause."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def console_main() -> None:
    """The ``gmmgp`` console script (``[project.scripts]``): :func:`main` on ``sys.argv``,
    then the process ends without the interpreter's teardown.

    Tearing down a process that imported numba, scipy and NumPy (module by module,
    every object freed) costs ~0.3-0.5 s after a run's work is done (docs/speed.md,
    session 10). So, once :func:`main` returned its code: the threads Python would
    wait for are joined and the ``atexit`` handlers run (logging, temporary folders,
    Dask clients), ``sys.stdout`` and ``sys.stderr`` are flushed, and ``os._exit(code)``
    ends the process: the same exit code and output, no teardown. Every file the
    commands write is complete and closed before they return (atomic renames). An
    exception that escapes :func:`main` (``--debug``) takes Python's normal path.
    """
    try:
        code = main()
    except SystemExit as exc:         # argparse: --help (0), bad arguments (2)
        code = _exit_code(exc.code)
    _exit_now(code)


def _exit_code(code) -> int:
    """What Python's own exit does with ``SystemExit(code)``: None is 0, an int is
    itself, anything else is printed to stderr and exits 1."""
    if code is None:
        return EXIT_OK
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


def _exit_now(code: int) -> None:
    import atexit
    import threading

    shutdown = getattr(threading, "_shutdown", None)   # what Python's exit does first:
    if shutdown is not None:                           # join non-daemon threads, stop
        shutdown()                                     # idle executors' workers
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:
                stream.flush()
        except (OSError, ValueError):     # a closed pipe or a full disk, as Python's exit
            if stream is sys.stdout and code == EXIT_OK:
                code = 120                # Python exits 120 when stdout cannot be flushed
    os._exit(code)


def _one_line(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror and exc.filename:
        msg = f"{exc.strerror}: '{exc.filename}'"
        if exc.errno == 28:
            msg += "; free some disk space or choose another --out"
        return msg
    text = str(exc) or type(exc).__name__
    return " ".join(text.split())


if __name__ == "__main__":
    console_main()
