"""The algorithm table: other RL libraries beside this project's trainers, from the reward alone, one budget per cell.

Cells (``OBS/TASK/ALGORITHM/sSEED``): from state, GraspLift and TableClearing x {SB3 PPO, SAC, TD3, DDPG, sb3-contrib
TQC, skrl PPO and SAC, this project's PPO} with each library's defaults, and ``TUNED_ALGOS``, each library algorithm
with its config from ``agents/configs`` (the settings these tasks need, each with its reason; the defaults rows stay, so
the tuning shows), ``STATE_ENV_STEPS`` of the task each; from the camera, GraspLift x {SB3 PPO, SB3 SAC, this project's
best camera recipe}, ``CAMERA_ENV_STEPS`` each. The budget is env steps (SB3's ``total_timesteps``, skrl's
``timesteps``, the trainers' ``--total-env-steps``), the wall clock and the host's reference speed recorded beside it,
``--max-minutes`` a guard; the cells run before that were held to ``STATE_BUDGET_MIN`` / ``CAMERA_BUDGET_MIN``
(``--budget-min`` still runs a cell so, for smoke runs), and their rows say so. A run whose cells should all be env-step
cells takes its own ``--out-dir``: a rerun skips the cells its JSON has.

Seed 1 everywhere; then, once a group (obs x task) has all its seed-1
cells, its best cell gets seeds ``--best-seeds`` (2 and 3). RHPO has a row that says why it is not run. ``ABLATIONS``
adds cells outside the defaults rule, one seed each and never a group's best: SB3 PPO from state on GraspLift with
the settings this project's PPO takes from ManiSkill's baseline, which asks how much of the defaults' zeros is
settings rather than library.

An env-step cell also scores its policy on the first ``--curve-episodes`` (30) held-out seeds every tenth of its
budget and at a quarter (``held_out_curve``, its evaluation time left out of the cell's clock), so the table reads
success at 25 %, 50 % and 100 % of the budget. Every cell is scored alike: 100 deterministic episodes on the held-out
seeds ``agents.common.EVAL_SEED`` onwards
(``agents.common.evaluate_on_seeds``, what every trainer here is scored on; training seeds stay below them), with a
95 % Wilson interval for one seed and ``benchmarks/learning.py``'s two-level bootstrap over seeds and episodes for
three. The library cells run through ``maniskill_irb120.integrations`` on ``--num-envs`` CPU worker envs with each
library's documented defaults for continuous control (``ALGORITHMS`` says which, and where a cell deviates and why);
the project's cells run ``benchmarks/learning.py``'s recipes (``ppo-state``; from the camera ``teacher-student-rgbd``,
a state PPO teacher learned from the reward and distilled into the camera policy, both stages within the cell's
budget).

Resumable, because the table is ~13 h on 2 cores (9 h of seed-1 cells, 4 h of the best cells' seeds 2 and 3, plus
1-5 min of evaluation a cell) and a session is shorter: the JSON keeps every finished cell and a rerun
skips them; a library cell checkpoints every ``--checkpoint-min`` and when Ctrl-C or SIGTERM stops it (exit 130)
(SB3: the model, and for state the replay buffer; skrl: the agent's modules), each time with the wall clock it has
spent, and a rerun continues it with the rest of its budget; a project cell continues with the trainer's own
``--resume``. A cell may be paused with ``kill -STOP`` (and ``-CONT``) while other work needs the cores: the minutes
it stood stopped are left out of its wall clock and kept beside it (``stopped_s``; the table's "and N stopped").
``--only`` picks cells by glob, ``--stop-after-min`` starts no cell that would end after it.

    python -m benchmarks.algorithms --update-results                          # every cell (resumes)
    python -m benchmarks.algorithms --only 'state/GraspLift/*' --stop-after-min 170 --update-results
    python -m benchmarks.algorithms --quick --out-dir /tmp/alg --only state/GraspLift/sb3-ppo/s1   # smoke run
    python -m benchmarks.algorithms --render-only   # the rows and section again from algorithms.json, no cell run
"""

from __future__ import annotations

import fnmatch
import json
import pickle
import platform
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from agents.common import EVAL_SEED, VALIDATION_SEED, evaluate_on_seeds, train_seed
from agents.common.checkpoints import atomic_save
from agents.common.evaluation import next_curve_share
from agents.recipes import RECIPES
from benchmarks.lib import budget, machine, runner
from benchmarks.lib.budget import rest_of
from benchmarks.lib.cli import entry
from benchmarks.lib.report import replace_section
from benchmarks.lib.stats import bootstrap_ci, iqm_ci, wilson
from benchmarks.lib.suspend import Suspensions
from maniskill_irb120.errors import terminate_as_interrupt
from maniskill_irb120.integrations.progress import Progress

ROOT = Path(__file__).resolve().parents[1]

TASKS = {"GraspLift": "GraspLift-IRB120-v1", "TableClearing": "TableClearing-IRB120-v1"}
STATE_ENV_STEPS = {"GraspLift": 500_000, "TableClearing": 1_000_000}
CAMERA_ENV_STEPS = 1_000_000
"""a cell's budget in env steps (issue 91's): the host's speed moved several-fold between days, so a minute budget
measured the machine as much as the library; the wall clock is recorded beside each cell, and --max-minutes guards it"""
STATE_BUDGET_MIN = 30.0
CAMERA_BUDGET_MIN = 60.0
"""the minutes the cells run before budgets were env steps were held to (their rows say so)"""
SB3_VERSION, SKRL_VERSION = "2.9.2", "2.1.1"  # pyproject.toml's sb3 and skrl extras


@dataclass(frozen=True)
class Algorithm:
    name: str
    library: str
    runner: str
    """sb3, skrl, project (a benchmarks/learning.py recipe as a subprocess) or none (cannot be run)"""
    settings: str
    """the hyperparameters, as the table prints them"""
    recipe: str = ""
    """the learning.py recipe of a project cell"""
    from_reward: bool = True
    ablation: bool = False
    """outside the table's rule of each library's defaults (a question about the others' zeros): never a group's best"""
    camera_settings: str = ""
    """the camera row's settings where they differ from ``settings`` (a tuned row's camera file)"""
    config: str = ""
    """a tuned row's algorithm in agents/configs (sb3/<config>.yml, skrl/<config>_<task>.yaml; skrl's defaults rows
    other than PPO's: skrl/<algo>_defaults.yaml, as <algo>-defaults); empty: the library's defaults in code"""


TUNED_OFF_POLICY = (
    "γ 0.8, τ 0.01, 4000 random env steps first, 2 updates per vector step (update-to-data 0.5), "
    "3x256, observations normalised (VecNormalize), absorbing success"
)
TUNED_SETTINGS = {
    "ppo": "γ 0.8, λ 0.9, n_steps 128/env, 8 epochs, target KL 0.1, 3x256 tanh, observations normalised "
    "(VecNormalize), absorbing success (AbsorbingSuccess wrapper), one log std from -0.5, the checkpoint selected on "
    "30 validation episodes every fortieth of the budget (SelectOnValidation)",
    "sac": TUNED_OFF_POLICY + ", initial temperature 0.1",
    "tqc": TUNED_OFF_POLICY + ", initial temperature 0.1",
    "td3": TUNED_OFF_POLICY + ", lr 3e-4, Gaussian action noise σ 0.1, action cost 0.1 x the arm's mean square "
    "(ActionPenalty, HER's action_l2)",
    "ddpg": TUNED_OFF_POLICY + ", lr 3e-4, Gaussian action noise σ 0.1, action cost 0.1 x the arm's mean square "
    "(ActionPenalty, HER's action_l2)",
    "skrl-ppo": "128 rollout steps/env, 8 minibatches, lr 3e-4, γ 0.8, λ 0.9, value loss 0.5, KL threshold 0.15 (SB3's "
    "target KL 0.1), no value clipping, 3x256 tanh, log std -0.5, RunningStandardScaler on observations, absorbing "
    "success, time_limit_bootstrap, the checkpoint selected on 30 validation episodes every fortieth of the budget "
    "(SelectOnValidation's skrl hook)",
    "skrl-sac": "γ 0.8, polyak 0.01, lr 3e-4, batch 256, 4000 random env steps, 2 updates per vector step, "
    "initial temperature 0.1, 3x256 ReLU, RunningStandardScaler, absorbing success",
}
"""the tuned rows' settings, as the table prints them (the files in agents/configs are what runs)"""
TUNED_CAMERA_SETTINGS = {
    "ppo": "agents/configs/sb3/ppo_rgbd.yml (rl-zoo3's format; each setting's why is its comment): sb3/ppo.yml's "
    "settings from the camera: MultiInputPolicy (NatureCNN on the 84x84 RGB-D image, the state vector beside it, "
    "3x256 tanh heads), the state vector normalised and the image not (VecNormalize norm_obs_keys), the checkpoint "
    "selected on 30 validation episodes every twentieth of the budget",
}
"""the camera rows' settings of the tuned configs with a camera file (agents/configs/loader.SB3_CAMERA_ALGOS)"""
SB3_OFF_POLICY_NOISE = "Gaussian action noise σ 0.1 (SB3's documented TD3/DDPG example; the class default has none)"
ALGORITHMS = {
    "sb3-ppo": Algorithm(
        "PPO", f"Stable-Baselines3 {SB3_VERSION}", "sb3",
        "SB3 defaults: n_steps 2048/env, batch 64, 10 epochs, lr 3e-4, γ 0.99, λ 0.95, clip 0.2, 2x64 tanh MLP "
        "(camera: NatureCNN + state); truncations bootstrapped (TimeLimit.truncated)",
    ),
    "sb3-sac": Algorithm(
        "SAC", f"Stable-Baselines3 {SB3_VERSION}", "sb3",
        "SB3 defaults: 1 update per vector step (of --num-envs env steps), batch 256, lr 3e-4, γ 0.99, τ 0.005, "
        "auto entropy, 100 random steps, 2x256 ReLU; camera: replay 30 000 (1e6 images would be 57 GB), otherwise 1e6",
    ),
    "sb3-td3": Algorithm(
        "TD3", f"Stable-Baselines3 {SB3_VERSION}", "sb3",
        "SB3 defaults: 1 update per vector step, batch 256, lr 1e-3, γ 0.99, τ 0.005, policy delay 2, 400-300 ReLU; "
        + SB3_OFF_POLICY_NOISE,
    ),
    "sb3-ddpg": Algorithm(
        "DDPG", f"Stable-Baselines3 {SB3_VERSION}", "sb3",
        "SB3 defaults: 1 update per vector step, batch 256, lr 1e-3, γ 0.99, τ 0.005, 400-300 ReLU; "
        + SB3_OFF_POLICY_NOISE,
    ),
    "sb3-ppo-maniskill": Algorithm(
        "PPO, ManiSkill's baseline settings (ablation)", f"Stable-Baselines3 {SB3_VERSION}", "sb3",
        "an ablation beside the defaults rule: SB3 PPO with the settings of the project's ppo-state recipe "
        "(ManiSkill's state-PPO baseline on 4 CPU workers): n_steps 128/env, batch 64, 8 epochs, lr 3e-4, γ 0.8, "
        "λ 0.9, target KL 0.1, 3x256 tanh actor and critic, log std -0.5 at the start, observations normalised "
        "(VecNormalize, rewards not); without the project's absorbing success, state-dependent noise and "
        "checkpoint selection",
        ablation=True,
    ),
    "skrl-ppo": Algorithm(
        "PPO", f"skrl {SKRL_VERSION}", "skrl",
        "skrl PPO_CFG defaults: 16 rollout steps/env, 8 epochs, 2 minibatches, lr 1e-3, γ 0.99, λ 0.95, "
        "value loss 2.5; time_limit_bootstrap on (the step limit is no failure); 2x256 ELU actor and critic; the "
        "policy scores its own Gaussian sample and the adapter clips it to the action bounds at the env, as SB3 does",
    ),
    "sb3-tqc": Algorithm(
        "TQC", f"sb3-contrib {SB3_VERSION}", "sb3",
        "sb3-contrib defaults: SAC's (1 update per vector step, batch 256, lr 3e-4, γ 0.99, τ 0.005, auto entropy, "
        "100 random steps) with 2 critics of 25 quantiles, the top 2 per critic dropped, 2x256 ReLU",
    ),
    **{
        f"sb3-{algo}-tuned": Algorithm(
            f"{algo.upper()}, tuned", f"{'sb3-contrib' if algo == 'tqc' else 'Stable-Baselines3'} {SB3_VERSION}",
            "sb3", f"agents/configs/sb3/{algo}.yml (rl-zoo3's format; each setting's why is its comment): "
            + TUNED_SETTINGS[algo], config=algo, camera_settings=TUNED_CAMERA_SETTINGS.get(algo, ""),
        )
        for algo in ("ppo", "sac", "tqc", "td3", "ddpg")
    },
    "skrl-sac": Algorithm(
        "SAC", f"skrl {SKRL_VERSION}", "skrl",
        "skrl SAC_CFG defaults (agents/configs/skrl/sac_defaults.yaml): 1 update per vector step, batch 64, lr 1e-3, "
        "γ 0.99, polyak 0.005, learned entropy from 0.2, no random steps; 2x256 ELU policy and critics (skrl has no "
        "default network: the PPO defaults row's), replay 1e6",
        config="sac-defaults",
    ),
    **{
        f"skrl-{algo}-tuned": Algorithm(
            f"{algo.upper()}, tuned", f"skrl {SKRL_VERSION}", "skrl",
            f"agents/configs/skrl/{algo}_<task>.yaml (skrl's runner YAML, as Isaac Lab's; each setting's why is its "
            "comment): " + TUNED_SETTINGS[f"skrl-{algo}"], config=algo,
        )
        for algo in ("ppo", "sac")
    },
    "project-ppo": Algorithm(
        "PPO", "this project (agents.ppo)", "project",
        "learning.py's ppo-state recipe: ManiSkill's state-PPO baseline settings, γ 0.8, observation normaliser, "
        "absorbing success, checkpoint selected on 30 validation seeds",
        recipe="ppo-state",
    ),
    "project-camera": Algorithm(
        "PPO teacher + DAgger student", "this project (agents.ppo, agents.dagger)", "project",
        "learning.py's teacher-student-rgbd recipe, the project's camera recipe from the reward alone: ppo-state "
        "learns a state teacher in 0.375 of the budget, DAgger distils it into the camera policy (agents.dagger "
        "--teacher) in the rest",
        recipe="teacher-student-rgbd",
    ),
}  # fmt: skip
NOT_RUNNABLE = {
    "RHPO": "not run: RHPO (Wulfmeier et al. 2020, the original report's future work) has no maintained "
    "implementation that we know of (none in Stable-Baselines3, skrl, RLlib, CleanRL or Acme)",
}
TUNED_ALGOS = ("sb3-sac-tuned", "sb3-ppo-tuned", "sb3-tqc-tuned", "sb3-td3-tuned", "skrl-ppo-tuned",
               "sb3-ddpg-tuned", "skrl-sac-tuned")  # fmt: skip
"""the rows of agents/configs' tuned settings, one per library algorithm, beside the defaults rows"""
STATE_ALGOS = ("sb3-ppo", "sb3-sac", "sb3-td3", "sb3-ddpg", "sb3-tqc", "skrl-ppo", "skrl-sac", "project-ppo",
               *TUNED_ALGOS)  # fmt: skip
CAMERA_ALGOS = ("sb3-ppo", "sb3-sac", "project-camera", "sb3-ppo-tuned")
"""the camera cells (GraspLift): the defaults rows, the project's recipe, and the library configs with a camera file
(agents/configs/loader.SB3_CAMERA_ALGOS)"""
ABLATIONS = (("state", "GraspLift", "sb3-ppo-maniskill"),)
"""(obs, task, algorithm) cells run after the grid's others, one seed each"""
SECTION_HEAD = "## RL libraries — `benchmarks/algorithms.py`"


@dataclass
class Args:
    only: list[str] = field(default_factory=list)
    """cells to run, as globs on OBS/TASK/ALGORITHM/sSEED (e.g. 'state/GraspLift/*', '*/sb3-sac/s1'); default all"""
    out_dir: Path = Path("benchmarks/results")
    """algorithms.json and algorithms.png go here"""
    runs_dir: Path = Path("runs/algorithms")
    """each cell's checkpoints, logs and (project cells) trainer runs"""
    num_envs: int = 4
    """CPU worker envs of the library cells (learning.py's ppo-state recipe runs 4 too)"""
    backend: str = "cpu"
    conf_file: Optional[Path] = None
    """a probe's config read by the tuned library cells instead of agents/configs' own (an rl-zoo3 hyperparams file
    for sb3-*-tuned, a runner YAML for skrl-*-tuned); give the probe its own --out-dir and --runs-dir"""
    best_seeds: list[int] = field(default_factory=lambda: [2, 3])
    """the seeds added to each group's best cell once its seed-1 cells are all in"""
    seeds: list[int] = field(default_factory=list)
    """more seeds of every --only cell, best or not (e.g. --seeds 2 3: the three seeds a target needs for a cell that
    is not its group's best)"""
    eval_episodes: int = 100
    curve_points: int = 10
    """held-out evaluations during an env-step cell, one every 1/curve_points of its budget and one at a quarter
    (the last is the final evaluation), so the table reads success at 25 %, 50 % and 100 % of the budget"""
    curve_episodes: int = 30
    """held-out episodes of each of those evaluations (seeds EVAL_SEED onwards, the final evaluation's first)"""
    total_env_steps: Optional[int] = None
    """env steps per cell instead of STATE_ENV_STEPS / CAMERA_ENV_STEPS"""
    max_minutes: Optional[float] = None
    """a wall-clock guard per cell (None: none); a cell it stops before its env steps says so ("stopped_early")"""
    budget_min: Optional[float] = None
    """minutes per cell as its budget instead of env steps, as the first cells ran (smoke runs)"""
    checkpoint_min: float = 10.0
    """a library cell saves what a rerun continues from this often"""
    progress_s: float = 60.0
    """seconds between a library cell's progress lines (env steps, their rate, ETA)"""
    stop_after_min: Optional[float] = None
    """start no cell whose budget would end after this many minutes of this run (one session's length)"""
    update_results: bool = False
    """rewrite this table's section of --results-md"""
    validate: bool = False
    """train nothing: score each --only cell's saved SB3 model (its --runs-dir checkpoint, as training left it) on
    --eval-episodes validation seeds (VALIDATION_SEED onwards, never the held-out ones) and add it to the cell as
    "validation", so that a choice between probes' configs reads no held-out episode"""
    render_only: bool = False
    """run no cell: the rows of algorithms.json in --out-dir again from its cells, and this table's section of
    --results-md"""
    results_md: Path = ROOT / "benchmarks" / "RESULTS.md"
    quick: bool = False
    """toy sizes: 3 s per cell (or --total-env-steps), 2 evaluation episodes, learning.py's --quick trainer flags,
    200 bootstrap resamples, a toy reference workload"""
    bootstrap: int = 10_000
    reference_steps: int = machine.REFERENCE_STEPS
    """steps of machine.reference_speed's fixed workload timed before and after each cell (0: none)"""


# ----------------------------------------------------------------------------- cells
def cell_id(obs: str, task: str, algo: str, seed: int) -> str:
    return f"{obs}/{task}/{algo}/s{seed}"


def parse_cell(cell: str) -> tuple[str, str, str, int]:
    obs, task, algo, seed = cell.split("/")
    return obs, task, algo, int(seed[1:])


def grid() -> list[tuple[str, str, str]]:
    """(obs, task, algorithm) of every cell, in the order they run."""
    state = [("state", task, algo) for task in TASKS for algo in STATE_ALGOS]
    return state + [("rgbd", "GraspLift", algo) for algo in CAMERA_ALGOS] + list(ABLATIONS)


def steps_of(obs: str, task: str, args: Args) -> Optional[int]:
    """A cell's budget in env steps, or None for one in minutes (``--budget-min``)."""
    if args.budget_min is not None:
        return None
    if args.total_env_steps is not None:
        return args.total_env_steps
    return STATE_ENV_STEPS[task] if obs == "state" else CAMERA_ENV_STEPS


def minutes_of(args: Args) -> Optional[float]:
    """A cell's minutes: its budget (``--budget-min``), else the guard (``--max-minutes``; None: none)."""
    return args.budget_min if args.budget_min is not None else args.max_minutes


def budget_text(minutes: Optional[float], steps: Optional[int]) -> str:
    """A cell's or row's budget as the table and the log print it."""
    if steps is None:
        return f"{minutes:g} min"
    return f"{steps:,} env steps" + ("" if minutes is None else f" (guard {minutes:g} min)")


def settings_of(obs: str, algo: str) -> str:
    """The row's settings as the table prints them: a camera row's own where its algorithm has them."""
    spec = ALGORITHMS[algo]
    return (obs != "state" and spec.camera_settings) or spec.settings


def best_algo(done: dict[str, dict], obs: str, task: str) -> Optional[str]:
    """The group's best reward-only algorithm by seed-1 success, once every seed-1 cell of the group is in.

    None where no seed-1 cell solved a held-out episode: a tie at 0 names no best, and seeds 2 and 3 of an arbitrary
    one would spend an hour to measure nothing. A tie above 0 goes to the algorithm earlier in the grid."""
    algos = [a for o, t, a in grid() if (o, t) == (obs, task) and not ALGORITHMS[a].ablation]
    if any(cell_id(obs, task, a, 1) not in done for a in algos):
        return None
    scored = [(done[cell_id(obs, task, a, 1)]["success_rate"], a) for a in algos if ALGORITHMS[a].from_reward]
    if not scored or max(rate for rate, _ in scored) == 0:
        return None
    top = max(rate for rate, _ in scored)
    return next(a for rate, a in scored if rate == top)


def planned(done: dict[str, dict], args: Args) -> list[str]:
    """Every cell this run would run now: seed 1 everywhere, the best-seed cells of finished groups; not done."""
    cells = [cell_id(o, t, a, 1) for o, t, a in grid()]
    for obs, task in dict.fromkeys((o, t) for o, t, _ in grid()):
        best = best_algo(done, obs, task)
        if best is not None:
            cells += [cell_id(obs, task, best, s) for s in args.best_seeds]
    cells += [cell_id(o, t, a, s) for o, t, a in grid() for s in args.seeds]
    cells = list(dict.fromkeys(cells))
    if args.only:
        cells = [c for c in cells if any(fnmatch.fnmatchcase(c, pattern) for pattern in args.only)]
    return [c for c in cells if c not in done]


def waiting_cells(done: dict[str, dict], args: Args) -> list[str]:
    """The --only cells when none of them is done or planned now: then they are best-seed cells of a group whose
    best is not known yet or is another algorithm, and the run would train nothing and end as if it had finished.
    Empty when any named cell runs or has run (a glob over a group names others' best seeds as well)."""
    if not args.only or planned(done, args):
        return []
    named = [c for c in all_cells(args) if any(fnmatch.fnmatchcase(c, p) for p in args.only)]
    return [] if any(c in done for c in named) else named


def all_cells(args: Args) -> list[str]:
    """Every cell the grid can hold, in its order: seed 1, --best-seeds and --seeds of each (obs, task, algo)."""
    return list(dict.fromkeys(cell_id(o, t, a, s) for o, t, a in grid() for s in [1, *args.best_seeds, *args.seeds]))


# ----------------------------------------------------------------------------- evaluation
def held_out(act: Callable, env_id: str, obs: str, args: Args, episodes: Optional[int] = None) -> dict:
    """``act`` on ``--eval-episodes`` (or ``episodes``) held-out seeds, as every trainer here is scored."""
    seeds = list(range(EVAL_SEED, EVAL_SEED + (args.eval_episodes if episodes is None else episodes)))
    r = evaluate_on_seeds(act, env_id, obs, seeds)
    return {k: r[k] for k in ("success_rate", "successes", "return", "episode_len") if k in r}


def library_obs(obs: str, flat: dict) -> object:
    """evaluate_on_seeds' observation (``{"state"}``, or ``rgb``/``depth``/``state``) as the adapters give it."""
    from maniskill_irb120.integrations.observations import image_state

    return flat["state"] if obs == "state" else image_state(flat)


def numpy_library_obs(obs: str, flat: dict) -> object:
    """:func:`library_obs` as numpy arrays, what SB3's ``predict`` takes."""
    o = library_obs(obs, flat)
    return {k: v.numpy() for k, v in o.items()} if isinstance(o, dict) else o.numpy()


# ----------------------------------------------------------------------------- library cells
READ_AT = (0.25, 0.5, 1.0)
"""the shares of the budget at which the table reads the held-out curve"""


class Budget:
    """A cell's wall clock across sessions: ``spent_s`` from earlier sessions plus this one's, against ``total_s`` (a
    minute budget or the guard; None: none); checkpoints due every ``every_s``. ``total_steps``: the cell's env-step
    budget, which the library's own step count keeps (SB3's ``total_timesteps``, skrl's ``timesteps``). Time the
    process spent stopped (``kill -STOP``, :mod:`benchmarks.lib.suspend`) is left out of ``spent_s`` and kept in
    ``stopped_s``, earlier sessions' (``stopped_before_s``) included."""

    def __init__(
        self,
        total_s: Optional[float],
        spent_s: float,
        every_s: float,
        total_steps: Optional[int] = None,
        stopped_before_s: float = 0.0,
    ):
        self.total_s, self.before_s, self.every_s, self.total_steps = total_s, spent_s, every_s, total_steps
        self.stopped_before_s = stopped_before_s
        self.t0 = self.last_save = time.time()
        self.suspensions = Suspensions()

    @property
    def stopped_s(self) -> float:
        return self.stopped_before_s + self.suspensions.total_s

    @property
    def spent_s(self) -> float:
        return self.before_s + time.time() - self.t0 - self.suspensions.total_s

    def over(self) -> bool:
        return self.total_s is not None and self.spent_s >= self.total_s

    def point_due(self, curve: list, steps: int = 0) -> bool:
        """A curve point every 1 % of the budget, env steps or minutes (``curve``'s rows: env steps, minutes,
        success)."""
        if not curve:
            return True
        if self.total_steps is not None:
            return steps - curve[-1][0] >= self.total_steps / 100
        return self.total_s is not None and self.spent_s / 60 - curve[-1][1] >= self.total_s / 60 / 100

    def eval_due(self, held: list, steps: int, points: int) -> bool:
        """A held-out curve point due: at each of :func:`curve_fractions` of an env-step budget (``held``'s rows: env
        steps, ...), the budget's end left to the final evaluation; never for a minute budget."""
        if self.total_steps is None:
            return False
        share = next_curve_share(points, self.total_steps, held)
        return share is not None and steps >= share * self.total_steps

    def pause(self, seconds: float) -> None:
        """Leave ``seconds`` (a held-out evaluation's) out of the cell's wall clock: it is not training."""
        self.t0 += seconds

    def save_due(self) -> bool:
        if time.time() - self.last_save >= self.every_s:
            self.last_save = time.time()
            return True
        return False


def progress_of(ckpt_dir: Path, env_steps: Optional[int], state: dict, args: Args) -> Optional[Progress]:
    """The cell's progress line (env steps of its budget, their rate this session, ETA, training success) every
    ``--progress-s`` seconds; None for a minute budget, whose cells keep a line every tenth of it."""
    if env_steps is None:
        return None
    cell = ckpt_dir.name.replace("__", "/")  # the run folder is the cell's name with its slashes doubled underscores
    return Progress(f"algorithms {cell}", env_steps, args.progress_s, start=state["env_steps"])


def read_state(ckpt_dir: Path) -> dict:
    path = ckpt_dir / "state.json"
    state = json.loads(path.read_text()) if path.is_file() else {"spent_s": 0.0, "env_steps": 0, "curve": []}
    state.setdefault("held_out", [])
    return state


def held_out_point(act: Callable, env_id: str, obs: str, args: Args, steps: int, clock: Budget, held: list) -> None:
    """One held-out curve point (``--curve-episodes`` seeds from EVAL_SEED) of the policy as it is now, appended to
    ``held`` as [env steps, training minutes, success, successes, evaluation seconds]; its time is left out of the
    cell's clock."""
    t, stopped = time.time(), clock.suspensions.total_s
    r = held_out(act, env_id, obs, args, args.curve_episodes)
    took = time.time() - t - (clock.suspensions.total_s - stopped)  # a stop meanwhile is already out of spent_s
    clock.pause(took)
    held.append([steps, clock.spent_s / 60, r["success_rate"], r["successes"], took])
    print(f"[algorithms] held out at {steps:,} env steps ({clock.spent_s / 60:.1f} min): success "
          f"{r['success_rate']:.2f} of {len(r['successes'])} ({took:.0f} s)", flush=True)  # fmt: skip


def write_json(path: Path, data: dict, indent: Optional[int] = None) -> None:
    """``data`` to ``path`` through a temporary file and a rename: a session killed mid-write leaves the old file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=indent))
    tmp.replace(path)


def write_state(ckpt_dir: Path, state: dict) -> None:
    write_json(ckpt_dir / "state.json", state)


def train_and_save(train: Callable[[], None], save: Callable[[], None]) -> None:
    """``train()``, then ``save()``. Ctrl-C or SIGTERM (which :func:`main` turns into Ctrl-C) during training saves the
    checkpoint too, with both signals ignored while it writes, before the interrupt goes on: a rerun continues from
    where the cell stopped, not from its last periodic save up to ``--checkpoint-min`` earlier."""
    try:
        train()
    except KeyboardInterrupt:
        with runner.signals_held():
            save()
        raise
    save()


def validate_sb3(cell: str, args: Args) -> dict:
    """A trained SB3 cell's saved model and observation statistics, deterministic, on --eval-episodes validation
    seeds (VALIDATION_SEED onwards: those checkpoint selection reads, never the held-out ones)."""
    from agents.configs import loader
    from maniskill_irb120.integrations.sb3 import deterministic_action

    obs, task, algo, _ = parse_cell(cell)
    spec = ALGORITHMS[algo]
    if spec.runner != "sb3":
        raise ValueError(f"--validate scores SB3 and skrl cells; {cell} is a {spec.runner} cell")
    ckpt_dir = args.runs_dir / cell.replace("/", "__")
    model_path, norm_path = ckpt_dir / "model.zip", ckpt_dir / "vecnormalize.pkl"
    if not model_path.is_file():
        raise ValueError(f"--validate: {cell} has no saved model at {model_path} (--runs-dir?)")
    model = loader.sb3_class(spec.config or algo.split("-")[1]).load(model_path, device="cpu")
    norm = pickle.loads(norm_path.read_bytes()) if norm_path.is_file() else None  # VecNormalize, without its envs

    def act(flat):
        return torch.as_tensor(deterministic_action(model, numpy_library_obs(obs, flat), norm))

    return on_validation(act, TASKS[task], obs, args, int(model.num_timesteps))


def on_validation(act: Callable, env_id: str, obs: str, args: Args, env_steps: int) -> dict:
    """``act`` on --eval-episodes validation seeds (VALIDATION_SEED onwards), as a cell's ``validation`` entry."""
    seeds = list(range(VALIDATION_SEED, VALIDATION_SEED + args.eval_episodes))
    r = evaluate_on_seeds(act, env_id, obs, seeds)
    lo, hi = wilson(int(sum(r["successes"])), len(seeds))
    return dict(success_rate=r["success_rate"], episodes=len(seeds), first_seed=VALIDATION_SEED, ci95=[lo, hi],
                env_steps=env_steps)  # fmt: skip


def run_sb3(
    algo: str,
    env_id: str,
    obs: str,
    seed: int,
    budget_s: Optional[float],
    ckpt_dir: Path,
    args: Args,
    env_steps: Optional[int] = None,
) -> dict:
    import stable_baselines3 as sb3
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.noise import NormalActionNoise
    from stable_baselines3.common.vec_env import VecNormalize

    from agents.configs import loader
    from maniskill_irb120.integrations.sb3 import deterministic_action, make_sb3_vec_env

    spec = ALGORITHMS[algo]
    tuned = loader.sb3_config(spec.config, env_id, args.conf_file, obs) if spec.config else None
    cls = loader.sb3_class(spec.config or algo.split("-")[1])
    policy = "MlpPolicy" if obs == "state" else "MultiInputPolicy"
    kwargs: dict = {}
    num_envs, wrappers, normalize = args.num_envs, [], None
    if tuned is not None:  # agents/configs/sb3/<algo>.yml, as rl-zoo3 would build it
        policy, num_envs, wrappers, normalize = tuned.policy, tuned.n_envs, tuned.wrappers, tuned.normalize
        kwargs.update(tuned.model_kwargs(n_actions=5))
    if algo == "sb3-ppo-maniskill":  # ALGORITHMS' settings text, as SB3 arguments
        kwargs.update(n_steps=128, batch_size=64, n_epochs=8, learning_rate=3e-4, gamma=0.8, gae_lambda=0.9,
                      target_kl=0.1, policy_kwargs=dict(net_arch=dict(pi=[256] * 3, vf=[256] * 3),
                                                        activation_fn=torch.nn.Tanh, log_std_init=-0.5))  # fmt: skip
    if algo in ("sb3-td3", "sb3-ddpg"):
        kwargs["action_noise"] = NormalActionNoise(np.zeros(5), 0.1 * np.ones(5))
    if cls is not sb3.PPO and obs != "state":
        kwargs["buffer_size"] = 30_000
    state = read_state(ckpt_dir)
    venv = make_sb3_vec_env(env_id, num_envs, obs, backend=args.backend, seed=train_seed(seed, 0), wrappers=wrappers)
    model_path, replay_path = ckpt_dir / "model.zip", ckpt_dir / "replay.pkl"
    norm_path = ckpt_dir / "vecnormalize.pkl"  # the running observation statistics, which the policy is trained on
    resumed = model_path.is_file()
    if algo == "sb3-ppo-maniskill":
        normalize = dict(norm_reward=False)
    if normalize is not None:
        venv = VecNormalize.load(str(norm_path), venv) if resumed else VecNormalize(venv, **normalize)
    if resumed:
        model = cls.load(model_path, env=venv)  # with its action noise, optimisers and counters
        if replay_path.is_file():
            model.load_replay_buffer(replay_path)
        print(f"[algorithms] continuing from {model_path} ({state['spent_s'] / 60:.1f} min spent)", flush=True)
    else:
        model = cls(policy, venv, seed=seed, verbose=0, tensorboard_log=str(ckpt_dir / "tb"), **kwargs)
    clock = Budget(budget_s, state["spent_s"], args.checkpoint_min * 60, env_steps, state.get("stopped_s", 0.0))
    curve, held = state["curve"], state["held_out"]
    progress = progress_of(ckpt_dir, env_steps, state, args)

    def act(flat):  # model and venv as bound when called: the selected policy is loaded without its envs, and
        # its statistics are the VecNormalize saved beside it (rebound below), not the model's (it has none)
        norm = venv if isinstance(venv, VecNormalize) else None
        return torch.as_tensor(deterministic_action(model, numpy_library_obs(obs, flat), norm))

    def save() -> None:
        model.save(model_path)
        if isinstance(venv, VecNormalize):
            venv.save(str(norm_path))
        if hasattr(model, "replay_buffer") and obs == "state":  # camera buffers are GBs: a resumed cell refills
            model.save_replay_buffer(replay_path)
        write_state(ckpt_dir, {"spent_s": clock.spent_s, "stopped_s": clock.stopped_s,
                               "env_steps": int(model.num_timesteps), "curve": curve, "held_out": held})  # fmt: skip

    class Stop(BaseCallback):
        def _on_step(self) -> bool:
            buf = self.model.ep_success_buffer
            steps = int(self.num_timesteps)
            if buf and clock.point_due(curve, steps):
                curve.append([steps, clock.spent_s / 60, float(np.mean(buf))])
                if progress is None and len(curve) % 10 == 1:
                    print(f"[algorithms] {steps:,} env steps, {clock.spent_s / 60:.1f} min: training episodes' "
                          f"success {np.mean(buf):.2f}", flush=True)  # fmt: skip
            if progress is not None:
                progress.tick(steps, lambda: f"training episodes' success {np.mean(buf):.2f}" if buf else "")
            if clock.eval_due(held, steps, args.curve_points):
                held_out_point(act, env_id, obs, args, steps, clock, held)
            if clock.save_due():
                save()
            return not clock.over()

    # SB3 counts env steps itself: learn() runs rollouts (PPO) or vector steps while num_timesteps is below its
    # total, which a resumed model counts on from (learn adds num_timesteps to it); the callback is the guard
    left = 10**12 if env_steps is None else env_steps - int(model.num_timesteps)

    # the config's own callbacks (rl-zoo3's ``callback:``), e.g. checkpoint selection on validation seeds, keeping
    # their files in the cell's folder, where a rerun's find them
    extra = tuned.make_callbacks(ckpt_dir / "best") if tuned is not None else []

    def train() -> None:
        if left > 0:
            model.learn(total_timesteps=left, callback=[Stop(), *extra], reset_num_timesteps=not resumed,
                        tb_log_name="run")  # fmt: skip

    try:
        train_and_save(train, save)
    finally:
        venv.close()
    env_steps, spent = int(model.num_timesteps), clock.spent_s
    # a selecting callback's best: this run's, or (training already over before this run) the one it kept on disk
    selector = next((c for c in extra if hasattr(c, "restore") and c.restore() is not None), None)
    if selector is None:
        final = held_out(act, env_id, obs, args)
        return dict(final, env_steps=env_steps, wall_clock_s=spent, stopped_s=clock.stopped_s, curve=curve_of(curve),
                    held_out_curve=held_out_curve(held, final, env_steps, spent))  # fmt: skip
    # the deployed policy is the selected one (its score is the cell's); the last one's is kept beside it, and the
    # curve's earlier points are the policy as it trained
    last = held_out(act, env_id, obs, args)
    best_dir = Path(selector.save_path)
    model = cls.load(best_dir / "best_model.zip", device="cpu")  # act reads model and venv as rebound here
    if (best_dir / "vecnormalize.pkl").is_file():  # the statistics saved with it; act uses only normalize_obs
        venv = pickle.loads((best_dir / "vecnormalize.pkl").read_bytes())
    final = held_out(act, env_id, obs, args)
    return dict(final, env_steps=env_steps, wall_clock_s=spent, stopped_s=clock.stopped_s, curve=curve_of(curve),
                held_out_curve=held_out_curve(held, final, env_steps, spent),
                selected=dict(selector.best, checks=selector.checks), last_policy_success=last["success_rate"],
                last_policy_successes=last["successes"])  # fmt: skip


def build_skrl(tuned: Optional[dict], env: Any, seed: int, experiment: dict, trainer_cfg: dict) -> tuple:
    """A cell's skrl agent and trainer on ``env``: a tuned config (``agents/configs/skrl/<algo>_<task>.yaml``)
    through skrl's own runner, as Isaac Lab runs it, or the PPO defaults row's agent (``tuned`` None)."""
    if tuned is not None:
        from agents.configs import loader
        from maniskill_irb120.integrations.skrl import make_runner

        tuned = loader.skrl_runner_config(tuned)
        tuned.update(seed=seed)
        tuned["agent"] = dict(tuned["agent"], experiment=experiment)
        tuned["trainer"] = dict(tuned["trainer"], **trainer_cfg)
        runner = make_runner(env, tuned)
        return runner.agent, runner.trainer
    from skrl.agents.torch.ppo import PPO, PPO_CFG
    from skrl.memories.torch import RandomMemory
    from skrl.trainers.torch import SequentialTrainer

    from maniskill_irb120.integrations.skrl import policy_and_value

    cfg = PPO_CFG(time_limit_bootstrap=True)
    for k, v in experiment.items():
        setattr(cfg.experiment, k, v)
    models = policy_and_value(env)
    memory = RandomMemory(memory_size=cfg.rollouts, num_envs=env.num_envs, device=env.device)
    agent = PPO(models=models, memory=memory, observation_space=env.observation_space,
                action_space=env.action_space, device=env.device, cfg=cfg)  # fmt: skip
    return agent, SequentialTrainer(env=env, agents=agent, cfg=trainer_cfg)


def skrl_act(agent: Any, observation_space: Any, obs: str) -> Callable:
    """The agent's deterministic action (``integrations.skrl.deterministic_action``, as its checkpoint selection
    plays it) from the flattened observation evaluate_on_seeds gives."""
    from maniskill_irb120.integrations.skrl import deterministic_action

    def act(flat):
        return deterministic_action(agent, observation_space, library_obs(obs, flat))

    return act


def load_skrl_cell(
    cell: str, agent_path: Path, conf_file: Optional[Path] = None, backend: str = "auto"
) -> tuple[Any, Any, Optional[dict]]:
    """A skrl cell's saved agent (``agent.pt``, or its selected ``best/best_agent.pt``: the models and the observation
    scaler), in evaluation mode, with the observation space it acts on and its tuned config (None: the defaults
    row's agent): what ``--validate`` and ``scripts/diagnose_policy.py`` play."""
    from agents.configs import loader
    from maniskill_irb120.integrations.skrl import make_skrl_env

    obs, task, algo, seed = parse_cell(cell)
    spec, env_id = ALGORITHMS[algo], TASKS[task]
    if spec.runner != "skrl":
        raise ValueError(f"{cell}: a {spec.library} cell, not a skrl one")
    if not agent_path.is_file():
        raise ValueError(f"{cell} has no saved agent at {agent_path} (--runs-dir?)")
    tuned = loader.skrl_config(spec.config, env_id, conf_file) if spec.config else None
    wrappers = loader.skrl_env_settings(tuned)[1] if tuned is not None else []
    env = make_skrl_env(env_id, 1, obs, backend=backend, seed=train_seed(seed, 0), wrappers=wrappers)
    try:
        experiment = dict(directory=str(agent_path.parent), experiment_name="validate", write_interval=0,
                          checkpoint_interval=0)  # fmt: skip
        trainer_cfg = dict(timesteps=1, headless=True, disable_progressbar=True, close_environment_at_exit=False)
        agent, _ = build_skrl(tuned, env, seed, experiment, trainer_cfg)
        agent.load(str(agent_path))
        agent.enable_models_training_mode(False)
        return agent, env.observation_space, tuned
    finally:
        env.close()


def validate_skrl(cell: str, args: Args) -> dict:
    """:func:`validate_sb3` for a skrl cell: its saved agent (models and observation scaler), deterministic, on
    --eval-episodes validation seeds."""
    obs, task = parse_cell(cell)[:2]
    agent_path = args.runs_dir / cell.replace("/", "__") / "agent.pt"
    try:
        agent, space, _ = load_skrl_cell(cell, agent_path, args.conf_file, args.backend)
    except ValueError as e:
        raise ValueError(f"--validate: {e}") from None
    act = skrl_act(agent, space, obs)
    return on_validation(act, TASKS[task], obs, args, read_state(agent_path.parent)["env_steps"])


def run_skrl(
    algo: str,
    env_id: str,
    obs: str,
    seed: int,
    budget_s: Optional[float],
    ckpt_dir: Path,
    args: Args,
    env_steps: Optional[int] = None,
) -> dict:
    from skrl.utils import set_seed

    from agents.configs import loader
    from maniskill_irb120.integrations.skrl import (
        SUCCESS_KEY,
        is_off_policy,
        make_skrl_env,
        off_policy_state,
        restore_off_policy_state,
    )

    set_seed(seed)
    state = read_state(ckpt_dir)
    spec = ALGORITHMS[algo]
    tuned = loader.skrl_config(spec.config, env_id, args.conf_file) if spec.config else None
    num_envs, wrappers = loader.skrl_env_settings(tuned) if tuned is not None else (args.num_envs, [])
    env = make_skrl_env(env_id, num_envs, obs, backend=args.backend, seed=train_seed(seed, 0), wrappers=wrappers)
    experiment = dict(directory=str(ckpt_dir), experiment_name="tb", write_interval=1000, checkpoint_interval=0)
    # skrl's timesteps are vector steps of num_envs env steps each, counted from 0 in every session: the rest of the
    # cell's env steps (at least one vector step's worth, so a finished budget trains nothing more than that)
    left = 10**10 if env_steps is None else max(1, -(-(env_steps - state["env_steps"]) // env.num_envs))
    trainer_cfg = {"timesteps": left, "headless": True, "disable_progressbar": True, "close_environment_at_exit": False}
    agent, trainer = build_skrl(tuned, env, seed, experiment, trainer_cfg)
    agent_path, replay_path = ckpt_dir / "agent.pt", ckpt_dir / "replay.pt"
    if agent_path.is_file():
        agent.load(str(agent_path))
        # an off-policy agent's replay memory and temperature, which agent.pt lacks (a cell saved before they were
        # kept has none: it goes on from an empty memory, and says so)
        if replay_path.is_file():
            restore_off_policy_state(agent, torch.load(replay_path, weights_only=False), state["env_steps"] // num_envs)
        elif is_off_policy(agent):
            print(f"[algorithms] {agent_path} has no replay memory beside it: continuing from an empty one", flush=True)
        print(f"[algorithms] continuing from {agent_path} ({state['spent_s'] / 60:.1f} min spent)", flush=True)
    clock = Budget(budget_s, state["spent_s"], args.checkpoint_min * 60, env_steps, state.get("stopped_s", 0.0))
    steps0, curve, recent, held = state["env_steps"], state["curve"], [], state["held_out"]
    progress = progress_of(ckpt_dir, env_steps, state, args)
    counted = {"steps": steps0}
    act = skrl_act(agent, env.observation_space, obs)
    # the config's own hooks (its ``callback:``), e.g. checkpoint selection on validation seeds, keeping their files in
    # the cell's folder, where a rerun finds them; attached first, so they run after the agent's update
    hooks = loader.skrl_callbacks(tuned, ckpt_dir / "best") if tuned is not None else []
    for hook in hooks:
        hook.attach(agent, env, env_id, obs, env_steps=steps0)

    def save() -> None:
        agent.save(str(agent_path))
        kept = off_policy_state(agent)
        if kept:  # written whole, then moved: a stop mid-write leaves the last one
            atomic_save(kept, replay_path)
        write_state(ckpt_dir, {"spent_s": clock.spent_s, "stopped_s": clock.stopped_s, "env_steps": counted["steps"],
                               "curve": curve, "held_out": held})  # fmt: skip

    class BudgetSpent(Exception):
        pass

    env_step, post = env.step, agent.post_interaction

    def step(actions):
        out = env_step(actions)
        counted["steps"] += env.num_envs
        if SUCCESS_KEY in out[4]["episode"]:
            recent.append(float(out[4]["episode"][SUCCESS_KEY]))
            del recent[:-25]
        return out

    def post_interaction(*, timestep: int, timesteps: int) -> None:
        post(timestep=timestep, timesteps=timesteps)  # skrl's update, when a rollout is full
        if recent and clock.point_due(curve, counted["steps"]):
            curve.append([counted["steps"], clock.spent_s / 60, float(np.mean(recent))])
            if progress is None and len(curve) % 10 == 1:
                print(f"[algorithms] {counted['steps']:,} env steps, {clock.spent_s / 60:.1f} min: training "
                      f"episodes' success {np.mean(recent):.2f}", flush=True)  # fmt: skip
        if progress is not None:
            progress.tick(
                counted["steps"], lambda: f"training episodes' success {np.mean(recent):.2f}" if recent else ""
            )
        if clock.eval_due(held, counted["steps"], args.curve_points):
            held_out_point(act, env_id, obs, args, counted["steps"], clock, held)
        if clock.save_due():
            save()
        if clock.over():
            raise BudgetSpent

    env.step, agent.post_interaction = step, post_interaction

    def train() -> None:
        if env_steps is not None and steps0 >= env_steps:
            return  # an earlier session trained the whole budget
        try:
            trainer.train()
        except BudgetSpent:
            pass

    try:
        train_and_save(train, save)
    finally:
        env.close()
    result = held_out(act, env_id, obs, args)
    spent = clock.spent_s
    steps = counted["steps"]
    cell = dict(result, env_steps=steps, wall_clock_s=spent, stopped_s=clock.stopped_s, curve=curve_of(curve),
                held_out_curve=held_out_curve(held, result, steps, spent))  # fmt: skip
    # a selecting hook's best (this run's, or the one kept on disk when training was over before this run) is the
    # deployed policy and its score the cell's; the last policy's is kept beside it, as run_sb3 keeps it
    selector = next((h for h in hooks if h.best is not None), None)  # attach restored what earlier sessions kept
    if selector is None:
        return cell
    agent.load(str(Path(selector.save_path) / "best_agent.pt"))  # act plays the agent as loaded
    final = held_out(act, env_id, obs, args)
    return dict(cell, **final, held_out_curve=held_out_curve(held, final, steps, spent),
                selected=dict(selector.best, checks=selector.checks), last_policy_success=result["success_rate"],
                last_policy_successes=result["successes"])  # fmt: skip


def held_out_curve(held: list, final: dict, env_steps: int, spent_s: float) -> dict:
    """The held-out curve: the points taken while training, then the final evaluation (its first
    ``--curve-episodes`` seeds are the points' seeds), each with its episodes' 95 % Wilson interval."""
    rows = [*held, [env_steps, spent_s / 60, final["success_rate"], final["successes"], None]]
    return dict(
        env_steps=[r[0] for r in rows],
        wall_min=[r[1] for r in rows],
        success=[r[2] for r in rows],
        episodes=[len(r[3]) for r in rows],
        ci95=[list(wilson(int(sum(r[3])), len(r[3]))) for r in rows],
        eval_s=[r[4] for r in rows],
    )


def curve_of(points: list) -> dict:
    """Training-episode success against env steps and wall clock, as learning.py's curves."""
    return dict(env_steps=[p[0] for p in points], wall_min=[p[1] for p in points], success=[p[2] for p in points])


# ----------------------------------------------------------------------------- project cells
def run_project(
    recipe: str,
    env_id: str,
    seed: int,
    budget_min: Optional[float],
    run_name: str,
    args: Args,
    env_steps: Optional[int] = None,
) -> dict:
    """learning.py's ``recipe`` in ``env_steps`` with ``budget_min`` as its guard, or without them in ``budget_min``:
    one trainer, or for a two-stage recipe (its ``base``) its base in its share of the budget (of env steps, the
    share its committed runs did: ``budget.base_steps``) and then the recipe's trainer, handed the base's checkpoint,
    in the rest; the cell's env steps, wall clock and curve are both stages' (``runner.joined``), as in learning.py's
    rows."""
    r = RECIPES[recipe].for_task(env_id)
    module, flags = r.trainer, r.argv()  # runner.run_trainer fills in the seed
    if r.base is None:
        if env_steps is not None:  # the trainer takes the held-out curve's points itself, as a library cell's
            flags = [*flags, "--curve-points", str(args.curve_points), "--curve-episodes", str(args.curve_episodes)]
        out = run_stage(module, flags, env_id, seed, budget_min, run_name, args, env_steps)
        held = out.pop("held_out_curve", None)
        if held is not None:
            out["held_out_curve"] = held_out_curve(held, out, out["env_steps"], out["wall_clock_s"])
        return out
    hand_on = f"--{r.base.hand_on}"
    base_recipe = RECIPES[r.base.recipe].for_task(env_id)
    base_flags, base_module = base_recipe.argv(), base_recipe.trainer
    if env_steps is None:
        base_min, base_steps = r.base.share * budget_min, None
    else:
        base_min, base_steps = budget_min, budget.base_steps(recipe, env_id, env_steps)
    base = run_stage(base_module, base_flags, env_id, seed, base_min, f"{run_name}__base", args, base_steps)
    rest = rest_of(budget_min, base["wall_clock_s"] / 60)  # an overrun shows in the cell's time
    rest_steps = None if env_steps is None else round(rest_of(env_steps, base["env_steps"]))
    tuned = run_stage(module, [*flags, hand_on, base["checkpoint"]], env_id, seed, rest, run_name, args, rest_steps)
    return runner.joined(base, tuned)


def run_stage(
    module: str,
    flags: list[str],
    env_id: str,
    seed: int,
    budget_min: Optional[float],
    run_name: str,
    args: Args,
    env_steps: Optional[int] = None,
) -> dict:
    """One trainer as a subprocess (``runner.run_trainer``), continued with its own ``--resume`` when an earlier
    session left a checkpoint and no result; a stage that finished in an earlier session (a two-stage cell stopped
    in its second) is read from the ``stage.json`` it left, not trained again."""
    runs = args.runs_dir / "project"
    done = runs / run_name / "stage.json"  # this function's result, written when the stage finished
    if done.is_file():
        print(f"[algorithms] {run_name}: finished earlier, read from {done}", flush=True)
        return json.loads(done.read_text())
    out = runner.run_trainer(
        run_name,
        module,
        flags,
        seed,
        budget_min,
        args,
        env_steps=env_steps,
        env_id=env_id,
        runs_dir=runs,
        logs_dir=args.runs_dir / "logs",
        resume=True,
    )
    done.write_text(json.dumps(out))
    return out


def run_cell(cell: str, args: Args) -> dict:
    obs, task, algo, seed = parse_cell(cell)
    spec, env_id = ALGORITHMS[algo], TASKS[task]
    minutes, steps = minutes_of(args), steps_of(obs, task, args)
    name = cell.replace("/", "__")
    print(f"[algorithms] {cell}: {budget_text(minutes, steps)}", flush=True)
    if spec.runner == "project":
        r = run_project(spec.recipe, env_id, seed, minutes, name, args, steps)
    else:  # the share of CPU time the host stole while it trained (a project cell's: runner.run_trainer's)
        runner = run_sb3 if spec.runner == "sb3" else run_skrl
        before = machine.cpu_times()
        r = runner(
            algo, env_id, obs, seed, None if minutes is None else minutes * 60, args.runs_dir / name, args, steps
        )
        steal = machine.steal_fraction(before, machine.cpu_times())
        if steal is not None:
            r["cpu_steal"] = steal
    if steps is None:
        r.update(budget_min=minutes)
    else:  # the budget, and whether the guard ended the cell before it
        r.update(total_env_steps=steps, max_minutes=minutes, stopped_early=r["env_steps"] < steps)
        r.pop("budget_min", None)
        if r["stopped_early"]:
            print(f"[algorithms] {cell}: stopped early at {r['env_steps']} env steps (of {steps})", flush=True)
    r.update(cell=cell, seed=seed, date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    if spec.runner != "project":  # a library learner's threads between steps from the camera (learner_threads_for):
        # torch's count at import, which a shared machine makes matter (docs/rl_libraries.md)
        from maniskill_irb120.vector import TORCH_THREADS

        r["torch_threads"] = TORCH_THREADS
    return r


# ----------------------------------------------------------------------------- statistics and report
def rows_of(cells: dict[str, dict], args: Args) -> list[dict]:
    """One row per (obs, task, algorithm): its seeds' mean success and interval, env steps and wall clock, or
    ``pending`` while its seed-1 cell is not in."""
    rng = np.random.default_rng(0)
    rows = []
    for obs, task, algo in grid():
        runs = sorted((c for c in cells.values() if parse_cell(c["cell"])[:3] == (obs, task, algo)),
                      key=lambda c: c["seed"])  # fmt: skip
        spec = ALGORITHMS[algo]
        row = dict(obs=obs, task=task, algorithm=algo, name=spec.name, library=spec.library,
                   settings=settings_of(obs, algo), from_reward=spec.from_reward, **row_budget(runs, obs, task, args),
                   seeds=[r["seed"] for r in runs])  # fmt: skip
        if runs:
            successes = [r["successes"] for r in runs]
            if len(runs) == 1:
                lo, hi = wilson(int(sum(successes[0])), len(successes[0]))
                interval = "Wilson"
            else:
                lo, hi = bootstrap_ci(successes, args.bootstrap, rng)
                interval = "bootstrap over seeds and episodes"
            row.update(
                success_mean=float(np.mean([r["success_rate"] for r in runs])),
                success_ci95=[lo, hi],
                interval=interval,
                per_seed=[r["success_rate"] for r in runs],
                env_steps_mean=float(np.mean([r["env_steps"] for r in runs])),
                wall_clock_min_mean=float(np.mean([r["wall_clock_s"] for r in runs])) / 60,
                stopped_min_mean=float(np.mean([r.get("stopped_s", 0.0) for r in runs])) / 60,  # not in the wall clock
            )
            row["held_out_at"] = held_out_at(runs)
            steal = [r["cpu_steal"] for r in runs if "cpu_steal" in r]
            row["cpu_steal_mean"] = float(np.mean(steal)) if steal else None  # None: not measured
            ref = [r["reference_sps"] for r in runs if "reference_sps" in r]
            row["reference_sps_mean"] = np.mean(ref, axis=0).round(1).tolist() if ref else None  # before, after
        rows.append(row)
    return rows


def held_out_at(runs: list[dict]) -> dict[str, Optional[float]]:
    """The seeds' mean held-out success at each of ``READ_AT``'s shares of the budget, from their held-out curves
    (None where a seed has no point there: a cell in minutes, or one run before the curve had that point)."""
    out: dict[str, Optional[float]] = {}
    for share in READ_AT:
        values = []
        for r in runs:
            curve, total = r.get("held_out_curve"), r.get("total_env_steps")
            if not curve or not total:
                break
            if share == 1.0:
                values.append(curve["success"][-1])
                continue
            at = [s for n, s in zip(curve["env_steps"][:-1], curve["success"][:-1]) if abs(n / total - share) < 0.02]
            if not at:
                break
            values.append(at[0])
        out[f"{share:g}"] = float(np.mean(values)) if values and len(values) == len(runs) else None
    return out


def row_budget(runs: list[dict], obs: str, task: str, args: Args) -> dict:
    """A row's budget: its cells' (env steps, or the minutes of a cell run before budgets were env steps), or for a
    pending row the one this run would give it."""
    if runs and all("total_env_steps" in r for r in runs):
        return dict(total_env_steps=runs[0]["total_env_steps"], budget_min=runs[0].get("max_minutes"))
    if runs:
        return dict(budget_min=runs[0]["budget_min"])
    steps = steps_of(obs, task, args)
    return dict(budget_min=minutes_of(args)) if steps is None else dict(total_env_steps=steps, budget_min=None)


def markdown(rows: list[dict]) -> str:
    lines = [
        "| obs | task | algorithm | library | seeds | success | 95 % CI | per seed | held out at 25 / 50 / 100 % "
        "| env steps | wall clock (min) | host steal | reference env steps/s, before / after | settings |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        name = r["name"] + ("" if r["from_reward"] else " (imitates the expert: reference)")
        head = f"| {r['obs']} | {r['task']} | {name} | {r['library']} |"
        if "success_mean" not in r:
            budget = budget_text(r["budget_min"], r.get("total_env_steps"))
            lines.append(f"{head} – | pending | | | | | ({budget} budget) | | | {r['settings']} |")
            continue
        lo, hi = r["success_ci95"]
        per = ", ".join(f"{x:.2f}" for x in r["per_seed"])
        steal = "–" if r.get("cpu_steal_mean") is None else f"{100 * r['cpu_steal_mean']:.0f} %"
        ref = "–" if r.get("reference_sps_mean") is None else " / ".join(f"{x:.0f}" for x in r["reference_sps_mean"])
        at = " / ".join("–" if v is None else f"{v:.2f}" for v in (r.get("held_out_at") or {}).values()) or "–"
        wall = f"{r['wall_clock_min_mean']:.1f}"
        if r.get("stopped_min_mean"):
            wall += f" (and {r['stopped_min_mean']:.1f} stopped)"
        lines.append(
            f"{head} {len(r['seeds'])} | {r['success_mean']:.2f} | [{lo:.2f}, {hi:.2f}] ({r['interval']}) | {per} | "
            f"{at} | {r['env_steps_mean']:,.0f} | {wall} | {steal} | {ref} | {r['settings']} |"
        )
    for name, why in NOT_RUNNABLE.items():
        lines.append(f"| state | – | {name} | – | – | – | – | – | – | – | – | – | – | {why} |")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = list(dict.fromkeys((r["obs"], r["task"]) for r in rows))
    fig, axes = plt.subplots(1, len(groups), figsize=(3.4 * len(groups), 3.2), dpi=80, sharey=True)
    for ax, (obs, task) in zip(np.atleast_1d(axes), groups):
        mine = [r for r in rows if (r["obs"], r["task"]) == (obs, task)]
        for i, r in enumerate(mine):
            if "success_mean" not in r:
                ax.text(i, 0.02, "pending", rotation=90, ha="center", va="bottom", fontsize=7, color="grey")
                continue
            lo, hi = r["success_ci95"]
            color = "C0" if r["from_reward"] else "grey"
            ax.bar(i, r["success_mean"], color=color, alpha=0.8)
            err = [[max(0.0, r["success_mean"] - lo)], [max(0.0, hi - r["success_mean"])]]  # Wilson's 1.0 rounds below
            ax.errorbar(i, r["success_mean"], yerr=err, color="k", capsize=3, lw=1)
        ax.set_xticks(range(len(mine)), [r["algorithm"] for r in mine], rotation=45, ha="right", fontsize=7)
        ax.set_xlim(-0.6, len(mine) - 0.4)
        ax.set(title=f"{obs}, {task} ({budget_text(mine[0]['budget_min'], mine[0].get('total_env_steps'))})",
               ylim=(0, 1.05))  # fmt: skip
        ax.title.set_fontsize(8)
    np.atleast_1d(axes)[0].set_ylabel("held-out success (95 % CI)")
    fig.suptitle("success on the held-out seeds, one budget per cell; grey: imitates the scripted expert", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def curves_of(cells: dict[str, dict], bootstrap: int) -> list[dict]:
    """Held-out success against env steps per (obs, task, algorithm) with env-step curves: at each share of the
    budget every seed has a point at (a tenth, the quarter, the end), the IQM over seeds and its two-level bootstrap
    interval (``stats.iqm_ci``). Cells of other budgets than the row's first seed's are left out."""
    rng = np.random.default_rng(0)
    out = []
    for obs, task, algo in grid():
        runs = sorted((c for c in cells.values() if parse_cell(c["cell"])[:3] == (obs, task, algo)
                       and c.get("held_out_curve") and c.get("total_env_steps")), key=lambda c: c["seed"])  # fmt: skip
        runs = [r for r in runs if runs and r["total_env_steps"] == runs[0]["total_env_steps"]]
        if not runs:
            continue
        total = runs[0]["total_env_steps"]
        per_run = []
        for r in runs:
            c = r["held_out_curve"]
            per_run.append({round(n / total * 40) / 40: (s, e) for n, s, e in zip(c["env_steps"], c["success"],
                                                                             c["episodes"])})  # fmt: skip
        shares = sorted(set.intersection(*(set(points) for points in per_run)))
        points = [iqm_ci([p[x][0] for p in per_run], [p[x][1] for p in per_run], bootstrap, rng) for x in shares]
        out.append(dict(obs=obs, task=task, algorithm=algo, name=ALGORITHMS[algo].name, seeds=[r["seed"] for r in runs],
                        total_env_steps=total, env_steps=[round(x * total) for x in shares],
                        iqm=[q[0] for q in points], ci95=[[q[1], q[2]] for q in points]))  # fmt: skip
    return out


def plot_curves(curves: list[dict], path: Path) -> None:
    """The curves of ``curves_of``, one panel per (obs, task): IQM over seeds and its 95 % interval shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = list(dict.fromkeys((c["obs"], c["task"]) for c in curves)) or [("state", "GraspLift")]
    fig, axes = plt.subplots(1, len(groups), figsize=(max(6.0, 4.2 * len(groups)), 3.6), dpi=80, sharey=True)
    for ax, (obs, task) in zip(np.atleast_1d(axes), groups):
        for i, c in enumerate(c for c in curves if (c["obs"], c["task"]) == (obs, task)):
            x = np.asarray(c["env_steps"]) / 1e3
            lo, hi = np.asarray(c["ci95"]).T
            ax.plot(x, c["iqm"], marker=".", color=f"C{i % 10}", label=f"{c['algorithm']} ({len(c['seeds'])} seeds)")
            ax.fill_between(x, lo, hi, color=f"C{i % 10}", alpha=0.15, lw=0)
        ax.set(title=f"{obs}, {task}", xlabel="env steps (thousands)", ylim=(-0.02, 1.02))
        ax.title.set_fontsize(9)
        if ax.lines:
            ax.legend(fontsize=6, loc="upper left")
    np.atleast_1d(axes)[0].set_ylabel("held-out success, IQM over seeds (95 % CI)")
    fig.suptitle("held-out success against env steps (30 episodes a point, 100 at the end)", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def update_results(report: dict, table: str, results: Path, json_path: Path, png_path: Path) -> None:
    """Replace (or append) this table's section of RESULTS.md."""

    def rel(p: Path) -> str:
        try:
            return str(p.resolve().relative_to(results.resolve().parent))
        except ValueError:
            return str(p.resolve())

    dates = sorted({c["date"] for c in report["cells"].values()})
    when = f"{dates[0]} to {dates[-1]}" if dates else "no cell yet"
    section = (
        f"{SECTION_HEAD}\n\n"
        "Other RL libraries beside this project's trainers, from the reward alone (the task's `normalized_dense`), "
        "one budget per cell, the env steps or minutes its row gives (cells in minutes were run before budgets were "
        f"env steps: {STATE_BUDGET_MIN:g} min from state, {CAMERA_BUDGET_MIN:g} min from the camera), on "
        f"{report['num_envs']} CPU worker envs; the final evaluation is extra, 1 seed per cell and 3 for "
        "each group's best (none where every seed-1 cell of the group scored 0); the ablation row is outside the "
        "defaults rule (its settings say which), one seed, and never a group's best; "
        f"{report['eval_episodes']} deterministic held-out episodes per run (seeds {EVAL_SEED}..). "
        "Host steal: the share of the machine's CPU time the hypervisor gave to other guests while the cell trained "
        "(its seeds' mean; a budgeted cell gets fewer env steps for it). Reference env steps/s: the machine's speed "
        "just before and after the cell, on one fixed workload (seeded random actions in 4 TableClearing state envs, "
        "`benchmarks.lib.machine.reference_speed`); this host's speed has moved several-fold between days while its "
        "steal read low, so compare env steps between cells as ratios to it. The library cells' learner runs on one "
        "torch thread while the envs step and, between steps, on the adapters' default (one from state, all of "
        "torch's from the camera: docs/rl_libraries.md). "
        "`python -m benchmarks.algorithms --update-results` runs every planned cell not yet in the raw data (split it "
        "over sessions with `--stop-after-min N`; an interrupted cell continues from its checkpoint), so the table "
        f"grew over several runs ({when}); each cell's date and trainer command are in the raw data. Last run: "
        f"`{report['command']}` ({report['machine']}); raw data: "
        f"[`{rel(json_path)}`]({rel(json_path)}).\n\n{table}\n\n![algorithm table]({rel(png_path)})\n\n"
        "Held-out success against env steps, the interquartile mean over seeds with a 95 % bootstrap interval "
        "(seeds, then each seed's episodes; rliable's aggregate, `benchmarks.lib.stats.iqm_ci`):\n\n"
        f"![success against env steps]({rel(png_path.with_name('algorithms_curves.png'))})\n\n"
    )
    replace_section(results, SECTION_HEAD, section)


def write_report(cells: dict[str, dict], args: Args, own: frozenset[str] = frozenset()) -> dict:
    """algorithms.json, its plots and (``--update-results``) its RESULTS.md section from ``cells`` and the cells a
    concurrent run of the same ``--out-dir`` wrote (read back under a lock, so that two lanes of cells side by side
    both keep theirs). The cells this run ran (``own``) win over the file's; any other is the file's, the newest:
    another lane adds its reference speed to its cell after the cell itself, and a copy read before that is stale."""
    import fcntl

    args.out_dir.mkdir(parents=True, exist_ok=True)
    with open(args.out_dir / ".algorithms.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        json_path = args.out_dir / "algorithms.json"
        if json_path.is_file():
            for key, cell in json.loads(json_path.read_text())["cells"].items():
                if key not in own:
                    cells[key] = cell
        return _write_report(cells, args)


def _write_report(cells: dict[str, dict], args: Args) -> dict:
    rows = rows_of(cells, args)
    report = dict(
        command="python -m benchmarks.algorithms " + " ".join(sys.argv[1:]),
        machine=f"{platform.node()} {platform.machine()}",
        num_envs=args.num_envs,
        eval_episodes=args.eval_episodes,
        state_budget_min=args.budget_min,
        camera_budget_min=args.budget_min,
        state_env_steps=None if args.budget_min is not None else {t: steps_of("state", t, args) for t in TASKS},
        camera_env_steps=steps_of("rgbd", "GraspLift", args),
        max_minutes=args.max_minutes,
        conf_file=None if args.conf_file is None else str(args.conf_file),
        versions=dict(stable_baselines3=SB3_VERSION, skrl=SKRL_VERSION, torch=torch.__version__),
        not_runnable=NOT_RUNNABLE,
        rows=rows,
        curves=curves_of(cells, args.bootstrap),
        cells=cells,
    )
    json_path, png_path = args.out_dir / "algorithms.json", args.out_dir / "algorithms.png"
    write_json(json_path, report, indent=1)
    plot(rows, png_path)
    plot_curves(report["curves"], args.out_dir / "algorithms_curves.png")
    table = markdown(rows)
    if args.update_results:
        update_results(report, table, args.results_md, json_path, png_path)
    return report


def run_cells(cells: dict[str, dict], args: Args, own: set[str]) -> None:
    """Run the planned cells in turn, adding each to ``cells`` (and its name to ``own``) and the report as it
    finishes, until none is left or the next would end after ``--stop-after-min``. Ctrl-C or SIGTERM: the cell keeps
    its checkpoint, exit 130."""
    t0 = time.time()
    while True:
        todo = planned(cells, args)
        if not todo:
            break
        cell = todo[0]
        if args.stop_after_min is not None:
            ends = (time.time() - t0) / 60 + (minutes_of(args) or 0.0)  # a cell without a guard: no estimate
            if ends > args.stop_after_min:
                print(f"[algorithms] stopping: {cell} would end at {ends:.0f} min > --stop-after-min", flush=True)
                break
        try:  # the machine's speed on machine.reference_speed's workload just before and after the cell
            before = machine.reference_speed(args.reference_steps, quick=args.quick)
            cells[cell] = run_cell(cell, args)
            own.add(cell)
        except (runner.Interrupted, KeyboardInterrupt):  # a cell's checkpoint is what a rerun continues from
            print(f"[algorithms] {cell}: interrupted; the same command continues it", flush=True)
            raise SystemExit(130) from None
        print(f"[algorithms] {cell}: success {cells[cell]['success_rate']:.2f}", flush=True)
        write_report(cells, args, frozenset(own))  # after every cell: a session that ends keeps what it finished
        try:
            after = machine.reference_speed(args.reference_steps, quick=args.quick)
        except KeyboardInterrupt:
            print(f"[algorithms] {cell}: interrupted while timing the reference after it; kept without it", flush=True)
            raise SystemExit(130) from None
        if before is not None:
            cells[cell]["reference_sps"] = [before, after]
            print(f"[algorithms] {cell}: reference env steps/s before and after: {before:g}, {after:g}", flush=True)
            write_report(cells, args, frozenset(own))


def writes_the_section(args: Args) -> bool:
    """Whether ``args.out_dir``'s table is the one RESULTS.md's section shows: the default folder's, or any folder's
    when ``--results-md`` is another file (a test's)."""
    default = args.out_dir == Args.out_dir or args.out_dir.resolve() == (ROOT / Args.out_dir).resolve()
    return default or args.results_md.resolve() != Args.results_md.resolve()


def check(args: Args) -> None:
    """Refuse flags that cannot run, each naming its flag, before any cell (``benchmarks.lib.cli`` makes it one line
    and exit status 2): a budget or guard that is not positive, an unknown backend, a negative reference workload, a
    --conf-file that is no file or shares the table's folders, an --only that matches no cell or only cells this run
    would not run (best seeds not due: ``waiting_cells``), a --render-only or
    --validate with no algorithms.json to read (or, validating, no cell of it named)."""
    if args.render_only:
        if not (args.out_dir / "algorithms.json").is_file():
            raise FileNotFoundError(f"--render-only reads {args.out_dir / 'algorithms.json'} (--out-dir), which does "
                                    "not exist")  # fmt: skip
        return
    if args.update_results and not writes_the_section(args):
        raise ValueError(
            f"--update-results writes RESULTS.md's {SECTION_HEAD[3:]!r} section, the table of {Args.out_dir}/; "
            f"--out-dir {args.out_dir} is another table (screening, full budget, a probe): drop --update-results"
        )
    if args.validate:
        json_path = args.out_dir / "algorithms.json"
        if not json_path.is_file():
            raise FileNotFoundError(f"--validate reads {json_path} (--out-dir), which does not exist")
        cells = json.loads(json_path.read_text())["cells"]
        if not any(fnmatch.fnmatchcase(c, p) for c in cells for p in args.only):
            raise ValueError(f"--validate: --only {args.only} names no cell of {json_path}")
    for flag, value in (("--total-env-steps", args.total_env_steps), ("--max-minutes", args.max_minutes),
                        ("--budget-min", args.budget_min), ("--progress-s", args.progress_s)):  # fmt: skip
        if value is not None and not value > 0:
            raise ValueError(f"{flag} must be positive, got {value}")
    if args.backend not in ("cpu", "gpu", "auto"):
        raise ValueError(f"--backend: unknown backend {args.backend!r}; use 'cpu', 'gpu' or 'auto'")
    if args.reference_steps < 0:
        raise ValueError(f"--reference-steps must be >= 0 (0: no reference), got {args.reference_steps}")
    if args.conf_file is not None:
        if not args.conf_file.is_file():
            raise ValueError(f"--conf-file {args.conf_file} is no file")
        if args.out_dir == Args.out_dir or args.runs_dir == Args.runs_dir:
            raise ValueError(
                "--conf-file is a probe's config: give it its own --out-dir and --runs-dir, so its cells "
                "do not join (or resume) the table's"
            )
    if any(s < 1 for s in [*args.seeds, *args.best_seeds]):
        raise ValueError(f"seeds are numbered from 1, got --seeds {args.seeds} --best-seeds {args.best_seeds}")
    if args.seeds and not args.only:
        raise ValueError("--seeds adds seeds to the --only cells: name them with --only (e.g. 'state/GraspLift/*')")
    known = set(all_cells(args))
    for pattern in args.only:
        if not any(fnmatch.fnmatchcase(c, pattern) for c in known):
            raise ValueError(f"--only {pattern!r} matches no cell; cells are OBS/TASK/ALGORITHM/sSEED, e.g. "
                             f"{sorted(known)[0]!r}")  # fmt: skip
    json_path = args.out_dir / "algorithms.json"
    if args.only and not args.render_only and not args.validate:
        done = json.loads(json_path.read_text())["cells"] if json_path.is_file() else {}
        waiting = waiting_cells(done, args)
        if waiting:
            seeds = " ".join(sorted({c.rsplit("/s", 1)[1] for c in waiting}, key=int))
            raise ValueError(
                f"--only {' '.join(args.only)} names {', '.join(waiting)}, which this run would not run: a seed of "
                f"--best-seeds runs only for its group's best algorithm once the group's seed-1 cells are in "
                f"{json_path}; add --seeds {seeds} to run it now"
            )


def main(args: Args) -> dict:
    check(args)
    if args.render_only:  # the rows again from the cells, so a settings text mended since shows in both files
        json_path = args.out_dir / "algorithms.json"
        report = json.loads(json_path.read_text())
        report["rows"] = rows_of(report["cells"], args)
        report["curves"] = curves_of(report["cells"], args.bootstrap)
        write_json(json_path, report, indent=1)
        plot(report["rows"], args.out_dir / "algorithms.png")
        plot_curves(report["curves"], args.out_dir / "algorithms_curves.png")
        if writes_the_section(args):
            update_results(
                report, markdown(report["rows"]), args.results_md, json_path, args.out_dir / "algorithms.png"
            )
        else:
            print(f"[algorithms] {json_path} rendered; RESULTS.md's section is the table of {Args.out_dir}/, "
                  "so it is left as it is", flush=True)  # fmt: skip
        return report
    if args.validate:
        json_path = args.out_dir / "algorithms.json"
        report = json.loads(json_path.read_text())
        cells = [c for c in report["cells"] if any(fnmatch.fnmatchcase(c, p) for p in args.only)]
        for cell in cells:
            validate = validate_skrl if ALGORITHMS[parse_cell(cell)[2]].runner == "skrl" else validate_sb3
            report["cells"][cell]["validation"] = v = validate(cell, args)
            print(f"[algorithms] {cell}: validation success {v['success_rate']:.2f} of {v['episodes']}", flush=True)
        write_json(json_path, report, indent=1)
        return report
    if args.quick:
        if args.budget_min is None and args.total_env_steps is None:  # toy minutes, unless toy env steps are given
            args.budget_min = 0.05
        args.eval_episodes, args.bootstrap, args.checkpoint_min = 2, 200, min(args.checkpoint_min, 0.02)
        args.curve_episodes = 1
    json_path = args.out_dir / "algorithms.json"
    cells: dict[str, dict] = json.loads(json_path.read_text())["cells"] if json_path.is_file() else {}
    own: set[str] = set()
    with terminate_as_interrupt():  # SIGTERM stops a cell as Ctrl-C does
        run_cells(cells, args, own)
    report = write_report(cells, args, frozenset(own))
    print(markdown(report["rows"]))
    left = planned(cells, args)
    print(f"[algorithms] {len(cells)} cells in {json_path}; {len(left)} planned now still to run", flush=True)
    return report


if __name__ == "__main__":
    entry("benchmarks.algorithms", Args, main, check)
