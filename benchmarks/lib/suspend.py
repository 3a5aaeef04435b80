"""Time a long benchmark run spent stopped, so its wall clock is the time it ran.

A cell of ``benchmarks.algorithms`` runs for hours beside other work, and is stopped (``kill -STOP``) while a CI run
has the cores, or with the laptop's lid. Its recorded wall clock would count those minutes as training. A daemon
thread wakes every ``tick_s`` on the monotonic clock; a wake-up that comes more than ``gap_s`` late means the
process did not run in between, since a Python thread that is merely starved (a busy CPU, a long C call holding the
GIL) is late by milliseconds to seconds, not half a minute. Those gaps, less one tick, are the stopped time.
"""

from __future__ import annotations

import threading
import time


class Suspensions:
    """``total_s``: seconds this process spent stopped since it was made (gaps over ``gap_s`` between ticks)."""

    def __init__(self, tick_s: float = 1.0, gap_s: float = 30.0):
        if not (0 < tick_s < gap_s):
            raise ValueError(f"Suspensions needs 0 < tick_s < gap_s, got tick_s={tick_s}, gap_s={gap_s}")
        self.tick_s, self.gap_s = float(tick_s), float(gap_s)
        self._total = 0.0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="suspensions", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(self.tick_s):
            now = time.monotonic()
            if now - last > self.gap_s:
                with self._lock:
                    self._total += now - last - self.tick_s
            last = now

    @property
    def total_s(self) -> float:
        with self._lock:
            return self._total

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5 * self.tick_s)
