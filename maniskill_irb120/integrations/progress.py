"""What a library's training run shows while it happens: a line every few seconds (env steps, their rate, the time
left) and, now and then, the policy's success on held-out seeds.

Lines, not a progress bar: a bar redraws one terminal row, so in a log file, under ``tee`` or in CI it is either
missing or thousands of carriage returns, and it says nothing of whether the policy learns. The same line every
``every_s`` seconds reads alike in both places, and a warm-up that trains nothing (SAC's ``learning_starts``) still
shows that it moves. The training-episode success a library logs is the stochastic policy's, with its exploration
noise; what a user deploys is the deterministic policy, so the held-out check steps that one on seeds training never
drew (``HELD_OUT_SEED`` onwards, the trainers' own held-out seeds).
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from typing import Any, Optional, TextIO

import numpy as np

from maniskill_irb120.integrations.observations import make_single_env

HELD_OUT_SEED = 10_000_000
"""the first held-out seed, ``agents.common.EVAL_SEED``'s value: the package may not import the trainers, and a test
holds the two equal"""

VALIDATION_SEED = 20_000_000
"""the first validation seed, ``agents.common.VALIDATION_SEED``'s value (checkpoint selection's episodes, apart from
training's and the held-out ones); a test holds the two equal"""

EVERY_S = 10.0
"""seconds between progress lines"""


def clock(seconds: float) -> str:
    """``seconds`` as a person reads a duration: ``42s``, ``7m05s``, ``1h02m``."""
    if not np.isfinite(seconds):
        return "?"
    s = int(round(max(seconds, 0.0)))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s % 3600 // 60:02d}m"


class Progress:
    """Prints ``[label] steps/total env steps (pct) | rate | elapsed, ETA | note`` at most every ``every_s`` seconds
    (:meth:`tick`) or at once (:meth:`report`). The rate is over the whole run so far, which an ETA needs; a run
    continued from a checkpoint at ``start`` env steps counts its rate from there, since the steps before it took
    another session's time."""

    def __init__(
        self, label: str, total: int, every_s: float = EVERY_S, stream: Optional[TextIO] = None, start: int = 0
    ):
        self.label, self.total, self.every_s, self.start = label, int(total), float(every_s), int(start)
        self.stream = stream
        self.started = self.last = time.perf_counter()

    def elapsed(self) -> float:
        return time.perf_counter() - self.started

    def line(self, steps: int, note: str = "") -> str:
        elapsed = self.elapsed()
        rate = (steps - self.start) / elapsed if elapsed > 0 else 0.0
        eta = (self.total - steps) / rate if rate > 0 else float("inf")
        pct = 100.0 * steps / self.total if self.total else 100.0
        text = (
            f"[{self.label}] {steps:,}/{self.total:,} env steps ({pct:.0f} %) | {rate:.1f} env steps/s | "
            f"{clock(elapsed)} elapsed, ETA {clock(eta)}"
        )
        return f"{text} | {note}" if note else text

    def report(self, steps: int, note: str = "") -> None:
        print(self.line(steps, note), file=self.stream or sys.stdout, flush=True)
        self.last = time.perf_counter()

    def tick(self, steps: int, note: Callable[[], str] = lambda: "") -> bool:
        """A line if ``every_s`` passed since the last one; ``note`` is only called then. True if it printed."""
        if time.perf_counter() - self.last < self.every_s:
            return False
        self.report(steps, note())
        return True


class Heartbeat:
    """While a phase runs that steps no env (a PPO update over its rollout: on the camera, a minute on 2 cores), a
    line every ``progress.every_s`` seconds saying so, from a daemon thread; the training loop's own lines need the
    loop to come round. ``with Heartbeat(progress, steps, "updating the policy"):``."""

    def __init__(self, progress: Progress, steps: int, what: str):
        self.progress, self.steps, self.what = progress, steps, what
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        started = time.perf_counter()
        while not self._stop.wait(max(self.progress.every_s - (time.perf_counter() - self.progress.last), 0.05)):
            if time.perf_counter() - self.progress.last >= self.progress.every_s:
                self.progress.report(self.steps, f"{self.what} ({clock(time.perf_counter() - started)} so far)")

    def __enter__(self) -> Heartbeat:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def held_out_success(
    act: Callable[[Any], np.ndarray],
    env_id: str,
    obs: str,
    episodes: int,
    *,
    seed: int = HELD_OUT_SEED,
    env_kwargs: Optional[dict] = None,
) -> int:
    """How many of ``episodes`` episodes (seeds ``seed``, ``seed + 1``, ...) ``act`` succeeds in: one CPU env with the
    adapters' observation (``make_single_env``), ``act`` taking one unbatched observation and giving one action,
    each episode run to its end; success is the task's on the last step (a success ends the episode)."""
    env = make_single_env(env_id, obs, env_kwargs=env_kwargs)
    wins = 0
    try:
        for k in range(episodes):
            o, _ = env.reset(seed=seed + k)
            while True:
                o, _, term, trunc, info = env.step(np.asarray(act(o), dtype=np.float32))
                if term or trunc:
                    break
            wins += bool(info["success"])
    finally:
        env.close()
    return wins
