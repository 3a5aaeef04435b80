"""Errors in what a user gave (a flag's value, a file, an env id): a :class:`UsageError` says what is wrong and how
to fix it in one line, and every command line (``maniskill-irb120``, ``examples/``) prints that line alone and exits
with status 2. Any other exception keeps its traceback, since it is a bug and the traceback says where. A SIGTERM to a
long run (:func:`terminate_as_interrupt`) ends it as a Ctrl-C does: what it trained saved, exit status 130.

Imports nothing of the package, so every layer (the wire side and ``policies/`` included) may raise these."""

from __future__ import annotations

import difflib
import io
import re
import signal
import sys
import threading
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from typing import TypeVar

T = TypeVar("T")


class UsageError(ValueError):
    """A bad input, named with its fix. A ValueError, so code that catches ValueError still does."""


class MissingFile(FileNotFoundError, UsageError):
    """A file the user named is not there. A FileNotFoundError too, so code that catches that still does."""


def nearest(given: str, choices: Iterable[str], cutoff: float = 0.6) -> str:
    """``" (did you mean 'X'?)"`` for the choice closest to ``given`` (difflib, case ignored), or ``""`` when none is
    as close as ``cutoff`` (difflib's ratio): the fix for a typo, ready to go inside a message."""
    by_lower = {c.lower(): c for c in choices}
    close = difflib.get_close_matches(given.lower(), list(by_lower), n=1, cutoff=cutoff)
    return f" (did you mean {by_lower[close[0]]!r}?)" if close else ""


def check_count(flag: str, value: int, least: int = 1) -> None:
    """A count (episodes, jobs, steps) refused below ``least``, naming the flag."""
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise UsageError(f"{flag} {value!r}: give a whole number >= {least}")


def say_usage_error(prog: str, error: UsageError) -> int:
    """Print ``prog: message`` to stderr, the message on one line; return the exit status 2."""
    print(f"{prog}: {' '.join(str(error).split())}", file=sys.stderr)
    return 2


@contextmanager
def usage_errors(prog: str) -> Iterator[None]:
    """Inside it, a UsageError ends the program with its one line on stderr and exit status 2 (a script's
    ``__main__`` block; library code raises and lets the caller decide)."""
    try:
        yield
    except UsageError as e:
        raise SystemExit(say_usage_error(prog, e)) from None


def _terminate(signum, frame) -> None:
    if callable(signal.getsignal(signal.SIGINT)):
        signal.raise_signal(signal.SIGINT)  # Python's handler: KeyboardInterrupt, or a hold's
    else:  # SIGINT ignored (or not Python's): raising it would do nothing
        raise KeyboardInterrupt


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Inside it, a SIGTERM (a scheduler's stop, a session's end, often sent to the whole process group) is a
    Ctrl-C, so the caller's ``KeyboardInterrupt`` path saves what it trained instead of dying with it. It goes
    through Python's SIGINT handler where there is one. Where SIGINT is ignored, as it is for a command started in
    the background by a script (``cmd &``: the shell ignores SIGINT for it), it is raised as is: a SIGTERM still
    stops the run. A pipe call of ``maniskill_irb120.vector`` holds either signal until its reply is read. Off the
    main thread, which alone may set a handler, it changes nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def tyro_error_line(box: str, prog: str) -> str:
    """tyro's error box (a malformed value, an unknown or a missing flag) as one line: its first section (what is
    wrong), the first flag of its "Perhaps you meant" list, and where the flags are listed."""
    sections: list[list[str]] = [[]]
    for line in box.splitlines():
        text = line.strip().strip("│╭╮╰╯").strip()
        if text and set(text) <= set("─ "):
            sections.append([])
        elif text and not line.strip().startswith(("╭", "╰")):  # not the box's top or bottom edge
            sections[-1].append(text)
    what = " ".join(sections[0]).rstrip(".")
    if what.startswith("Missing from"):  # each missing flag with its metavar and help: the flags say enough
        what = "missing " + ", ".join(re.findall(r"--[\w-]+", what))
    meant = next((s for s in sections if s and s[0].startswith("Perhaps you meant")), [])
    flag = re.search(r"--[\w-]+", " ".join(meant[1:2]))
    return f"{what}{f' (did you mean {flag.group(0)}?)' if flag else ''}; {prog} --help lists the flags"


def parse_flags(args_type: type[T], prog: str, argv: Sequence[str] | None = None) -> T:
    """``tyro.cli(args_type)`` for a script's flags, with tyro's error box (a malformed value, an unknown flag) said
    in one line on stderr and exit status 2; ``--help`` as tyro prints it."""
    import tyro

    stderr, held = sys.stderr, io.StringIO()
    sys.stderr = held
    try:
        return tyro.cli(args_type, prog=prog, args=argv)
    except SystemExit as e:
        if e.code in (0, None) or not held.getvalue().strip():
            raise
        print(f"{prog}: {tyro_error_line(held.getvalue(), prog)}", file=stderr)
        raise SystemExit(2) from None
    finally:
        sys.stderr = stderr
        if held.getvalue() and not held.getvalue().lstrip().startswith("╭"):  # a warning, not an error box
            stderr.write(held.getvalue())
