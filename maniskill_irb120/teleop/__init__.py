"""Teleoperation: devices (keyboard in a terminal, SpaceMouse, gamepad) behind one ``Device`` interface, the loop
that drives a task and records its episodes as ManiSkill trajectories (``sim``), and jogging a robot through
``ABBRobot`` (``jog``).

May import ``action``, ``robot/``, ``envs/``, ``experts/`` and ``abb/``; never ``sim2real/`` or ``agents/``.
``devices``, ``keyboard``, ``spacemouse``, ``gamepad`` and ``jog`` import neither ManiSkill nor SAPIEN: a robot
PC jogs the robot with them."""
