"""Tasks on the shared IRB 120 table scene; importing registers them with ManiSkill (and gymnasium)."""

from maniskill_irb120.envs.grasp_lift import GraspLiftIRB120Env
from maniskill_irb120.envs.stack_cube import StackCubeIRB120Env
from maniskill_irb120.envs.table_clearing import TableClearingIRB120Env

__all__ = ["GraspLiftIRB120Env", "StackCubeIRB120Env", "TableClearingIRB120Env"]
