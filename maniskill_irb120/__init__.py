"""ABB IRB 120 + MetalWork gripper testbed for ManiSkill 3. Importing registers the agent and tasks."""

__version__ = "0.1.0"

from maniskill_irb120 import (
    agents,  # noqa: F401,E402  (registers irb120_metalwork)
    envs,  # noqa: F401,E402  (registers TableClearing-IRB120-v1)
)
from maniskill_irb120.vector import make_vec_env  # noqa: E402

__all__ = ["make_vec_env", "__version__"]
