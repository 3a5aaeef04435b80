"""A test stand-in for an IRC5: ``controller.py`` runs the shipped RAPID modules with ``rapid/`` (a RAPID
interpreter) and the controller's routines (``builtins.py``) on ``robot.py`` (an emulated IRB 120), serving a pty or
a loopback socket (``channel.py``); ``rws.py`` serves Robot Web Services 1.0 over it. May import the wire side
(``abb.protocol``), ``robot/`` and ``action``; never ``envs/`` or above. See docs/emulator.md.
"""
