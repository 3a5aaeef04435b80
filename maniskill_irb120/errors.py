"""Errors in what a user gave (a flag's value, a file, an env id): a :class:`UsageError` says what is wrong and how
to fix it in one line, and every command line (``maniskill-irb120``, ``examples/``) prints that line alone and exits
with status 2. Any other exception keeps its traceback, since it is a bug and the traceback says where.

Imports nothing of the package, so every layer (the wire side and ``policies/`` included) may raise these."""

from __future__ import annotations

import difflib
import sys
from collections.abc import Iterable, Iterator
from contextlib import contextmanager


class UsageError(ValueError):
    """A bad input, named with its fix. A ValueError, so code that catches ValueError still does."""


class MissingFile(FileNotFoundError, UsageError):
    """A file the user named is not there. A FileNotFoundError too, so code that catches that still does."""


def nearest(given: str, choices: Iterable[str]) -> str:
    """``" (did you mean 'X'?)"`` for the choice closest to ``given`` (difflib, case ignored), or ``""`` when none is
    close: the fix for a typo, ready to go inside a message."""
    by_lower = {c.lower(): c for c in choices}
    close = difflib.get_close_matches(given.lower(), list(by_lower), n=1, cutoff=0.6)
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
