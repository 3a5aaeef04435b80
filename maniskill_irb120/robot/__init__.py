from maniskill_irb120.agents.irb120 import IRB120Metalwork

__all__ = ["IRB120Metalwork"]
