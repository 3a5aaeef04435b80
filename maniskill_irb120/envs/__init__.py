"""Tasks; importing registers them with ManiSkill (and gymnasium)."""

from maniskill_irb120.envs.table_clearing import TableClearingIRB120Env

__all__ = ["TableClearingIRB120Env"]
