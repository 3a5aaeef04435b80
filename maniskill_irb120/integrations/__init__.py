"""Adapters that hand the tasks to other RL libraries: Stable-Baselines3 (``integrations.sb3``) and skrl
(``integrations.skrl``), both over :func:`maniskill_irb120.vector.make_vec_env` (CPU worker processes or the
GPU-batched ``physx_cuda`` env) and the flat observation of ``integrations.observations``. docs/rl_libraries.md
shows their use.

Imports: the package's own layers (``envs``, ``vector``, ``wrappers``) and, inside the adapter that needs it, the
library it adapts (an optional extra: ``pip install .[sb3]`` or ``.[skrl]``); never ``agents/`` or
``benchmarks/``, and no other package layer imports this one. Importing ``maniskill_irb120.integrations`` itself
needs neither library.
"""

from maniskill_irb120.integrations.observations import (
    DEPTH_MM_PER_LEVEL,
    OBS_KINDS,
    ImageStateObservation,
    image_state,
    make_single_env,
    make_vector_env,
    observation_wrappers,
)

__all__ = [
    "DEPTH_MM_PER_LEVEL",
    "OBS_KINDS",
    "ImageStateObservation",
    "image_state",
    "make_single_env",
    "make_vector_env",
    "observation_wrappers",
]
