"""Scripted experts for the tasks (one pick-and-place phase machine, a subclass per task, registered by env id),
the episode loop that rolls them out, and demo recording in ManiSkill's trajectory format.

May import ``envs/``, ``robot/``, ``action``; never ``sim2real/``, ``abb/`` or ``agents/``."""

from maniskill_irb120.experts.pick_place import EXPERTS, PickPlaceExpert, expert_for, register_expert

__all__ = ["EXPERTS", "PickPlaceExpert", "expert_for", "register_expert"]
