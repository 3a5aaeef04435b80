"""The ABB side, what a robot PC runs: the wire protocol, the client (``ABBRobot``), the safety envelope and the
deployment over Robot Web Services (``deploy.py``, with abb-robot-client), plus the controller emulator
(``abb/emulator``: our RAPID executed on an emulated IRC5, for CI and dry runs).

The wire side (everything here but ``emulator/``) imports neither ManiSkill nor SAPIEN, only ``action`` and
``robot.kinematics`` / ``robot.description``: a robot PC needs no simulator. Nothing here imports ``envs/``,
``sim2real/`` or ``agents/``."""
