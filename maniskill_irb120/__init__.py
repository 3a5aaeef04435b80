"""ABB IRB 120 + MetalWork gripper testbed for ManiSkill 3. Importing registers the agent and the tasks.

The folders are the layers, each importing only those below it (``tests/test_layers.py`` holds them to it):
``action.py`` (the action space: numpy/torch only) < ``robot/`` (the IRB 120 as a ManiSkill agent, its
controllers and kinematics) < ``envs/`` (the tasks) < ``vector.py``, ``wrappers.py`` < ``experts/`` (scripted
experts, demos) < ``sim2real/`` (ManiSkill's Sim2RealEnv on the robot, policies, evaluation, sysid), with
``integrations/`` (Stable-Baselines3 and skrl over ``vector.py``) on top, imported by no other layer; beside
them ``abb/``, the wire side a robot PC runs (protocol, client, envelope: no ManiSkill, no SAPIEN) and its
controller emulator. Trainers live outside the package, in ``agents/``.
"""

__version__ = "0.1.0"

try:
    import mani_skill  # noqa: F401
except ModuleNotFoundError as e:  # a robot PC with the wire side only: maniskill_irb120.abb works without it
    if e.name != "mani_skill":
        raise
    _MISSING = e
else:
    _MISSING = None
    from maniskill_irb120 import envs  # noqa: F401  (registers the agent and every task)
    from maniskill_irb120.vector import make_vec_env

__all__ = ["make_vec_env", "__version__"]


def __getattr__(name: str):
    if name == "make_vec_env" and _MISSING is not None:
        raise ImportError(f"make_vec_env needs ManiSkill, which is not installed here ({_MISSING})")
    raise AttributeError(f"module 'maniskill_irb120' has no attribute {name!r}")
