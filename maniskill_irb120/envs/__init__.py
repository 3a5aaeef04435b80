"""Tasks on the shared IRB 120 table scene; importing registers them with ManiSkill (and gymnasium)."""

from __future__ import annotations

from maniskill_irb120.envs.grasp_lift import GraspLiftIRB120Env
from maniskill_irb120.envs.stack_cube import StackCubeIRB120Env
from maniskill_irb120.envs.table_clearing import TableClearingIRB120Env
from maniskill_irb120.errors import UsageError, nearest

__all__ = ["GraspLiftIRB120Env", "StackCubeIRB120Env", "TableClearingIRB120Env", "check_env_id", "task_ids"]


def task_ids() -> list[str]:
    """This package's tasks as ManiSkill's registry has them (every env id whose class is ours), sorted."""
    from mani_skill.utils.registration import REGISTERED_ENVS

    return sorted(k for k, spec in REGISTERED_ENVS.items() if spec.cls.__module__.startswith(__name__))


def check_env_id(env_id: str) -> str:
    """``env_id`` if gymnasium knows it (ManiSkill's own tasks too), else a UsageError naming this package's tasks
    and the nearest id, instead of gymnasium's NameNotFound deep in an env's construction."""
    import gymnasium as gym

    if env_id in gym.registry:
        return env_id
    ours = task_ids()
    # among every registered id only a near-exact one (PickCube-v2 -> PickCube-v1), not any id that shares "-v1"
    hint = nearest(env_id, ours) or nearest(env_id, gym.registry, cutoff=0.8)
    raise UsageError(f"unknown env id {env_id!r}{hint}; this package's tasks: {', '.join(ours)}")
