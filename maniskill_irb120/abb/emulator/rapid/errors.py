"""RAPID error numbers and the exceptions the interpreter raises: a *recoverable* RAPID error
(:class:`RapidError`, carries an ``errno`` and goes to the routine's ERROR handler) and a *fatal* one
(:class:`RapidRuntimeError`: an unhandled RAPID error, or a program fault, which on the IRC5 stops the program).
See docs/rapid_subset.md, "Errors and recovery".
"""

from __future__ import annotations

# Our numeric codes (the ABB manuals are not at hand, so these are NOT ABB's values): programs compare ERRNO
# with the names, never with the numbers. User codes 1..90 are free for ``RAISE n``; BookErrNo starts at 1000.
ERROR_CODES: dict[str, int] = {
    "ERR_ALRDYCNT": 101,  # interrupt variable already connected
    "ERR_ARGVALERR": 102,  # argument value out of range (Sqrt(-1), StrPart past the end, bad IntX ...)
    "ERR_DIVZERO": 103,  # division by zero (/, DIV, MOD)
    "ERR_NOTPRES": 104,  # an optional parameter that was not given is read
    "ERR_OUTOFBND": 105,  # array index or rawbytes index outside its bounds
    "ERR_STRTOOLNG": 106,  # string longer than 80 characters
    "ERR_DEV_MAXTIME": 110,  # ReadRawBytes / ReadBin ... \Time expired
    "ERR_FILEOPEN": 111,  # Open failed (device or file)
    "ERR_FILEACC": 112,  # device or file access failed
    "ERR_RANYBIN_EOF": 113,  # end of file / channel closed while reading
    "ERR_RANYBIN_CHK": 114,  # checksum error while reading
    "ERR_SOCK_TIMEOUT": 120,  # socket operation \Time expired
    "ERR_SOCK_CLOSED": 121,  # peer closed the socket
    "ERR_SOCK_ADDR_INUSE": 122,  # SocketBind: address in use
    "ERR_ROBLIMIT": 130,  # joint limit exceeded (CalcJointT, MoveL ...)
    "ERR_OUTSIDE_REACH": 131,  # target outside the robot's reach
    "ERR_WAIT_MAXTIME": 132,  # WaitUntil/WaitDI \MaxTime expired
    "ERR_PATH_STOP": 133,  # movement stopped
}
USER_ERRNO_BASE = 1000  # first number BookErrNo hands out


class RapidError(Exception):
    """A recoverable RAPID error: raise it from a Python builtin to enter the routine's ERROR handler."""

    def __init__(self, errno: int | str, message: str = ""):
        if isinstance(errno, str):
            errno = ERROR_CODES[errno.upper()]
        self.errno = int(errno)
        self.message = message
        self.routine: str | None = None  # where it first happened (set by the interpreter)
        self.line: int | None = None
        super().__init__(f"RAPID error {self.errno}{': ' + message if message else ''}")


class RapidRuntimeError(Exception):
    """A fatal error: an unhandled RAPID error (``errno`` set) or a program fault (``errno`` None)."""

    def __init__(self, message: str, *, errno: int | None = None, routine: str | None = None, line: int | None = None):
        self.errno = errno
        self.routine = routine
        self.line = line
        where = f" (routine {routine}, line {line})" if routine else (f" (line {line})" if line else "")
        super().__init__(message + where)


class RapidSyntaxError(Exception):
    """The module does not parse; ``line``/``column`` point at the offending token."""

    def __init__(self, message: str, line: int, column: int):
        self.line, self.column = line, column
        super().__init__(message)


class RapidLoadError(RapidSyntaxError):
    """The controller refuses to load the task's modules: a name of an option that is not installed, or an
    ambiguous (twice declared) global name. ``module``, ``line`` and ``name`` locate it; ``options`` lists the
    RobotWare options (``"616-1 PC Interface"``) any one of which would provide the name (empty otherwise)."""

    def __init__(self, message: str, *, module: str, line: int, name: str, options: tuple[str, ...] = ()):
        self.module, self.name, self.options = module, name, options
        super().__init__(f"module {module}, line {line}: {message}", line, 0)


class RapidStopped(Exception):
    """The program was stopped from outside (:meth:`Interpreter.request_stop`) or ran out of statement budget."""


class ProgramHalt(Exception):
    """Raised by ``EXIT`` and ``Stop``: ends :meth:`Interpreter.run` normally (``kind`` is 'exit' or 'stop')."""

    def __init__(self, kind: str):
        self.kind = kind
        super().__init__(kind)


def errno_name(errno: int) -> str:
    """The ERR_* name of a code (for messages), or the number itself."""
    for name, code in ERROR_CODES.items():
        if code == errno:
            return name
    return str(errno)
