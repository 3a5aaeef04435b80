"""A RAPID-subset interpreter (ABB IRC5 robot language) so the controller-side module can run in CI without a robot.

``Interpreter(source, builtins).run("main")`` executes a module; robot built-ins (MoveL, CRobT, serial and socket
I/O ...) are Python callables registered in a :class:`Builtins` registry. See ``docs/rapid_subset.md``.
"""

from maniskill_irb120.abb.emulator.rapid.errors import (
    ERROR_CODES,
    RapidError,
    RapidLoadError,
    RapidRuntimeError,
    RapidStopped,
    RapidSyntaxError,
)
from maniskill_irb120.abb.emulator.rapid.interpreter import Interpreter
from maniskill_irb120.abb.emulator.rapid.options import OPTIONS, RobotWareOption, parse_options
from maniskill_irb120.abb.emulator.rapid.parser import parse
from maniskill_irb120.abb.emulator.rapid.registry import Builtin, Builtins
from maniskill_irb120.abb.emulator.rapid.stdlib import ManualClock, SystemClock
from maniskill_irb120.abb.emulator.rapid.values import (
    ClockVar,
    Opaque,
    RawBytes,
    Record,
    Ref,
    define_record,
    make_value,
)

__all__ = [
    "ERROR_CODES",
    "OPTIONS",
    "Builtin",
    "Builtins",
    "ClockVar",
    "Interpreter",
    "ManualClock",
    "Opaque",
    "RapidError",
    "RapidLoadError",
    "RapidRuntimeError",
    "RapidStopped",
    "RapidSyntaxError",
    "RawBytes",
    "RobotWareOption",
    "Record",
    "Ref",
    "SystemClock",
    "define_record",
    "make_value",
    "parse",
    "parse_options",
]
