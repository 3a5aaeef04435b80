"""Checkpoint selection on validation seeds, the part every library's hook shares.

PPO on GraspLift peaks and then unlearns (the project's PPO, SB3's and skrl's alike), so the last policy is not the
one to deploy. The libraries' own choices do not fit: SB3's ``EvalCallback`` and skrl's runner keep the best *mean
reward*, and on these tasks an episode that holds the object without succeeding out-earns one that succeeds, since a
success ends the episode. :class:`ValidationSelection` keeps the best by *success* instead: every ``every`` env steps
the deterministic policy plays ``episodes`` validation episodes (seeds ``seed`` onwards, ``VALIDATION_SEED``: apart
from training's and the held-out ones, so the selected policy's held-out score is not the score it was chosen by),
and the best so far is saved in ``save_path`` (by the library's hook: the model file is the library's) with
``best.json`` (its env steps, success and every check), which a resumed run reads to go on from.

The hooks: ``integrations.sb3.SelectOnValidation`` (an SB3 callback, an rl-zoo3 ``callback:`` entry) and
``integrations.skrl.SelectOnValidation`` (around an skrl agent's ``post_interaction``, a ``callback:`` entry of the
project's skrl YAML).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, Optional

from maniskill_irb120.integrations.progress import VALIDATION_SEED, held_out_success


class ValidationSelection:
    """The schedule, the score and the record of checkpoint selection (the module doc says why); the library's hook
    supplies the policy's action, its env steps and how to save the model."""

    def __init__(self, every: int, episodes: int = 30, save_path: str = "best_on_validation",
                 seed: int = VALIDATION_SEED, verbose: int = 1):  # fmt: skip
        name = type(self).__name__
        try:
            every, episodes, seed = int(every), int(episodes), int(seed)
        except (TypeError, ValueError):
            raise ValueError(f"{name}: every ({every!r}), episodes ({episodes!r}) and seed ({seed!r}) must be "
                             "integers") from None  # fmt: skip
        if every <= 0 or episodes <= 0:
            raise ValueError(f"{name}: every ({every}) and episodes ({episodes}) must be positive")
        self.every, self.episodes, self.seed = every, episodes, seed
        self.save_path, self.verbose = Path(save_path), verbose
        self.best: Optional[dict] = None
        self.checks: list[list] = []
        self._next = self.every

    @property
    def best_file(self) -> Path:
        return self.save_path / "best.json"

    def restore(self) -> Optional[dict]:
        """The best so far and the checks from ``save_path`` (a resumed run's, or one whose training had already
        ended); None where nothing was kept yet."""
        if self.best_file.is_file():
            kept = json.loads(self.best_file.read_text())
            self.best, self.checks = kept["best"], kept["checks"]
        return self.best

    def start(self, env_steps: int) -> None:
        """Before training (again): restore what was kept, and schedule the next check after both ``env_steps``
        (where the run stands) and the last check kept, so a resumed run neither repeats nor skips one."""
        self.restore()
        done = self.checks[-1][0] if self.checks else 0
        self._next = max(self.every, (max(int(env_steps), done) // self.every + 1) * self.every)

    def due(self, env_steps: int) -> bool:
        """Whether a check is due at ``env_steps``; one is taken per crossing, however many ``every`` a step jumps."""
        if env_steps < self._next:
            return False
        self._next = (int(env_steps) // self.every + 1) * self.every
        return True

    def validate(self, env_steps: int, act: Callable[[Any], Any], env_id: str, obs: str,
                 save_best: Callable[[Path], None]) -> tuple[float, bool]:  # fmt: skip
        """``act`` (one unbatched adapter observation to one action) on the validation episodes now; where it beats
        the best so far (ties go to the earlier, as the project's trainers select), ``save_best(save_path)`` saves
        the model. Returns the success rate and whether it became the best."""
        wins = held_out_success(act, env_id, obs, self.episodes, seed=self.seed)
        rate = wins / self.episodes
        self.checks.append([int(env_steps), rate])
        improved = self.best is None or rate > self.best["success"]
        self.save_path.mkdir(parents=True, exist_ok=True)
        if improved:
            save_best(self.save_path)
            self.best = dict(env_steps=int(env_steps), success=rate, episodes=self.episodes, first_seed=self.seed)
        tmp = self.best_file.with_name("best.json.tmp")  # written whole, then moved: never half a record
        tmp.write_text(json.dumps(dict(best=self.best, checks=self.checks)))
        tmp.replace(self.best_file)
        if self.verbose:
            best = self.best
            print(f"[select] {int(env_steps):,} env steps: validation success {wins}/{self.episodes} (seeds "
                  f"{self.seed}..); best {best['success']:.2f} at {best['env_steps']:,}", flush=True)  # fmt: skip
        return rate, improved
