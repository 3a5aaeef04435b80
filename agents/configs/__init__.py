"""The RL libraries' configs for these tasks, where each library's users look for them, and their loader.

``sb3/<algo>.yml``: Stable-Baselines3 (and sb3-contrib's TQC) in rl-zoo3's hyperparams format, keyed by env id;
``skrl/<algo>_<task>.yaml``: skrl's runner YAML, as Isaac Lab keeps ``agents/skrl_*_cfg.yaml`` beside each task.
They sit beside the trainers, out of the installed package, as the project's own recipes do; every setting that
differs from the library's default carries a comment saying why (a test checks). :mod:`agents.configs.loader` turns
them into the library's objects (rl-zoo3 does not install beside this stack: docs/rl_libraries.md says why).
"""
