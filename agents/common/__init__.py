"""What every trainer in ``agents/`` shares besides the policy networks (those live in the library,
``maniskill_irb120.policies``): the common flags and ``--recipe`` (``args``), the envs and observation layout
(``envs``), the replay storage (``buffers``), checkpoint writes, reads and RNG state (``checkpoints``), the held-out
evaluation every recipe is scored on (``evaluation``), the loggers (``logging``), mixed precision (``precision``)
and the frame of a run: its folder, resume, budget clock, checkpoint and final evaluation (``run``). It may import
the library ``maniskill_irb120`` and third-party packages, never a trainer (``agents.ppo``, ``agents.sac``,
``agents.dagger``, ``agents.rllib``): trainers import it and the library, never each other."""

from agents.common.args import RunArgs, cli, recipe_argv
from agents.common.buffers import Dataset, prune_row_files, restore_dataset
from agents.common.checkpoints import args_json, atomic_save, load_for_evaluation, load_torch, rng_state, set_rng_state
from agents.common.envs import (
    AUX_DIM,
    ExpertLabels,
    action_wrappers,
    flatten_obs,
    make_envs,
    obs_to,
    one_thread_beside_workers,
    privileged_aux,
    resolve_device,
    shapes_of,
    torch_threads,
    vec_envs,
)
from agents.common.evaluation import (
    EVAL_SEED,
    EVENT_KEYS,
    REWARD_TERM_PREFIX,
    VALIDATION_SEED,
    EpisodeTracker,
    evaluate_checkpoint,
    evaluate_on_seeds,
    new_eval_dir,
    train_seed,
)
from agents.common.logging import Logger, budget_bar, finish
from agents.common.precision import PRECISIONS, autocast, resolve_precision
from agents.common.run import (
    Budget,
    Clock,
    check_resume_signature,
    checkpoint,
    close_and_save,
    evaluate_and_finish,
    held_out_evaluation,
    open_run,
    restore,
)

__all__ = [
    "AUX_DIM",
    "Budget",
    "Clock",
    "EVAL_SEED",
    "EVENT_KEYS",
    "PRECISIONS",
    "REWARD_TERM_PREFIX",
    "VALIDATION_SEED",
    "Dataset",
    "EpisodeTracker",
    "ExpertLabels",
    "Logger",
    "RunArgs",
    "action_wrappers",
    "args_json",
    "atomic_save",
    "autocast",
    "budget_bar",
    "check_resume_signature",
    "checkpoint",
    "cli",
    "close_and_save",
    "evaluate_and_finish",
    "evaluate_checkpoint",
    "evaluate_on_seeds",
    "finish",
    "flatten_obs",
    "held_out_evaluation",
    "load_for_evaluation",
    "load_torch",
    "make_envs",
    "new_eval_dir",
    "obs_to",
    "one_thread_beside_workers",
    "open_run",
    "privileged_aux",
    "prune_row_files",
    "recipe_argv",
    "resolve_device",
    "resolve_precision",
    "restore",
    "restore_dataset",
    "rng_state",
    "set_rng_state",
    "shapes_of",
    "torch_threads",
    "train_seed",
    "vec_envs",
]
