"""Distributed training on Ray RLlib (extra ``ray``): ``python -m agents.rllib --help``.

``env`` (the env creator and the next-step autoreset adapter), ``module`` (our RGB-D encoder in RLlib's
default modules), ``callbacks`` (task metrics), ``checkpoint`` (atomic checkpoints, the trained module without
Ray), ``train`` (``build_config`` and the CLI)."""
