"""A stand-in for a virtual IRC5: ``controller.py`` runs the shipped RAPID module with ``rapid/`` (a RAPID
interpreter) on ``robot.py`` (an emulated IRB 120 moving over wall-clock time), serving a pty or a loopback
socket. May import the wire side (``abb.protocol``), ``robot/`` and ``action``; never ``envs/`` or above."""
