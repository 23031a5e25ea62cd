"""Console progress: stage lines and a minimal progress bar on stderr.

No third-party dependency; quiet when ``enabled`` is False (tests, --quiet).
"""

from __future__ import annotations

import sys
import time


class ProgressBar:
    """``bar = ProgressBar(total, "GP blocks"); bar.update(n); bar.close()``.

    Redraws in place on a terminal; on a pipe prints at most every 10 %.
    """

    def __init__(self, total: int, desc: str, stream=None, enabled: bool = True):
        self.total, self.desc = max(int(total), 1), desc
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.n = 0
        self.t0 = time.perf_counter()
        self._tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self._last_decile = -1

    def update(self, n: int = 1) -> None:
        self.n = min(self.n + n, self.total)
        if not self.enabled:
            return
        frac = self.n / self.total
        if self._tty:
            width = 30
            fill = int(frac * width)
            self.stream.write(f"\r  {self.desc} [{'#' * fill}{'.' * (width - fill)}] "
                              f"{self.n}/{self.total} {time.perf_counter() - self.t0:5.1f}s")
            self.stream.flush()
        elif int(frac * 10) > self._last_decile:
            self._last_decile = int(frac * 10)
            self.stream.write(f"  {self.desc}: {self.n}/{self.total}\n")

    def close(self) -> None:
        if self.enabled and self._tty:
            self.stream.write("\n")
            self.stream.flush()


class ConsoleObserver:
    """Pipeline observer printing one line per stage with its time and counts."""

    def __init__(self, stream=None, enabled: bool = True):
        self.stream = stream or sys.stderr
        self.enabled = enabled

    def on_stage_start(self, name: str) -> None:
        if self.enabled:
            self.stream.write(f"[{name}] running ...\n")
            self.stream.flush()

    def on_stage(self, name: str, payload) -> None:
        if not self.enabled:
            return
        self.stream.write(f"[{name}] done in {payload.seconds:.2f} s\n")
        msg = (getattr(payload, "extra", None) or {}).get("message")
        if msg:
            self.stream.write(f"[{name}] {msg}\n")
        self.stream.flush()

    def progress(self, total: int, desc: str) -> ProgressBar:
        return ProgressBar(total, desc, self.stream, self.enabled)
