"""The policies a trained checkpoint deploys, as torch modules with no training code: the shared encoders and
the deterministic actor (``nets``), PPO's actor-critic (``ppo``), the SAC model (``sac``), and a checkpoint's
self-describing policy section with the acting function built from it alone (``section``). The trainers in
``agents/`` import these classes and write the section; ``sim2real`` reads it. This package imports only
torch and numpy (and ``maniskill_irb120.action`` should a policy need the action space), never ``agents``."""

from maniskill_irb120.policies.section import (
    MODULES,
    acting,
    policy_module,
    policy_section,
    read_checkpoint,
    read_policy_section,
    section_of,
)

__all__ = [
    "MODULES",
    "acting",
    "read_checkpoint",
    "policy_module",
    "policy_section",
    "read_policy_section",
    "section_of",
]
