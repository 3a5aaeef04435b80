"""The IRB 120 + MetalWork gripper: its description (URDF from xacro, low-polygon meshes), kinematics (batched FK
and IK, numpy/torch only), the ManiSkill agent (``irb120.py``), its controllers and its camera shaders.

May import ``maniskill_irb120.action`` and ``maniskill_compat``; never ``envs/`` or anything above. ``kinematics``
and ``description`` import neither ManiSkill nor SAPIEN: the wire side (``abb/``) uses them on a robot PC, so
this ``__init__`` imports nothing (the agent registers when ``robot.irb120`` is imported, as ``envs`` does)."""
