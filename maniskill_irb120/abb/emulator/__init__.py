"""A stand-in for a virtual IRC5: ``controller.py`` runs the shipped RAPID modules with ``rapid/`` (a RAPID
interpreter) and the controller's built-ins (``builtins.py``) on ``robot.py`` (an emulated IRB 120 moving over
wall-clock time), serving a pty or a loopback socket (``channel.py``); ``rws.py`` serves Robot Web Services 1.0
over it (what ``deploy`` talks to). May import the wire side (``abb.protocol``), ``robot/`` and ``action``; never
``envs/`` or above."""
