"""Sim-to-real on ManiSkill's ``Sim2RealEnv``: the IRB 120's real agent (over ``abb``), cameras (RealSense, the
twin's render), the digital twin behind the emulator, policies from any trainer's checkpoint, the side-by-side
evaluation and its report, and system identification from its logs.

The top layer of the library: may import everything in it; ``agents/`` (the trainers) never."""
