"""What the in-process profilers of ``gmmgp`` commands share (scripts/profile_run.py,
profile_run_parts.py, profile_first_calls.py): their command line (own options, then
``--`` and the ``gmmgp`` command they run in this process), the pipeline's stage events
as timers, and the process's resident memory (Linux ``/proc``)."""

from __future__ import annotations

import resource
import threading
import time


def parse_command(ap, argv, *, need_out: bool = False):
    """``(args, cli)``: ``argv`` before ``--`` parsed by ``ap``, and the ``gmmgp`` command
    after it (refused when absent, or without ``--out`` when ``need_out``)."""
    ours, cli = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv \
        else (argv, [])
    args = ap.parse_args(ours)
    if need_out and (not cli or "--out" not in cli):
        ap.error("give the gmmgp command after '--' with --out, e.g. -- run SCAN --out DIR -q")
    if not cli:
        ap.error("give the gmmgp command after '--', e.g. -- run SCAN --out DIR -q")
    return args, cli


def hook_stage_events(on_start, on_end) -> None:
    """Call ``on_start(name)`` as each pipeline stage starts and ``on_end(name)`` as it
    ends (``pipeline.FanoutObserver``'s events, which every run's observer goes
    through), before the observers."""
    from gmmgp_app import pipeline

    fanout = pipeline.FanoutObserver
    orig_start, orig_stage = fanout.on_stage_start, fanout.on_stage

    def on_stage_start(self, name):
        on_start(name)
        return orig_start(self, name)

    def on_stage(self, name, payload):
        on_end(name)
        return orig_stage(self, name, payload)

    fanout.on_stage_start, fanout.on_stage = on_stage_start, on_stage


def time_stages(add) -> None:
    """``add(name, wall s, process CPU s)`` for each pipeline stage that ran (its start
    to its end event)."""
    started = {}

    def start(name):
        started[name] = (time.perf_counter(), time.process_time())

    def end(name):
        if name in started:
            t0, c0 = started.pop(name)
            add(name, time.perf_counter() - t0, time.process_time() - c0)

    hook_stage_events(start, end)


def rss_mb() -> float:
    """The process's resident set size now (MB; ``VmRSS`` of ``/proc/self/status``)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def maxrss_mb() -> float:
    """The process's peak resident set size so far (MB; ``ru_maxrss``)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class Sampler(threading.Thread):
    """Samples :func:`rss_mb` every ``period`` s into ``samples`` ``(t, MB)`` until
    ``stop`` is set."""

    def __init__(self, period: float):
        super().__init__(daemon=True)
        self.period = period
        self.samples = []          # (t, rss MB)
        self.stop = threading.Event()

    def run(self):
        while not self.stop.is_set():
            self.samples.append((time.perf_counter(), rss_mb()))
            time.sleep(self.period)
