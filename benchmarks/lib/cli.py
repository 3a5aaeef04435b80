"""A benchmark's command line end: bad input is one line on stderr and exit status 2, never a traceback.

Each benchmark's ``if __name__ == "__main__":`` calls :func:`entry` with its ``Args``, its ``check`` and its ``main``.
``check`` refuses what cannot run (a count below its least, an unknown choice, a file that is not there) by raising
ValueError or FileNotFoundError naming the flag, and does so before anything heavy (no env is built), so that a
script chaining benchmarks reads one reason within seconds instead of a traceback after minutes. What ``main`` raises
keeps its traceback: past the check, an exception is a bug or a failed run, and the traceback says where. A Ctrl-C
ends in one line and exit status 130, as the trainers' (``agents.common.args.entry``), so a chain of commands stops.

tyro's own refusals (an unknown flag, a malformed value) are one line and status 2 too. The one-line form of its
error box comes from ``maniskill_irb120.errors``, imported only then: that package imports ManiSkill, seconds that
a benchmark which needs none of it (``headline``, ``sim_speed``) should not spend on every start."""

from __future__ import annotations

import io
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Optional, TypeVar

A = TypeVar("A")

INPUT_ERRORS = (ValueError, FileNotFoundError)
"""what a ``check`` raises for a flag that cannot run"""


def rendered_from(path: Path, flag: str) -> None:
    """A ``--render-only`` check: FileNotFoundError naming ``flag`` unless ``path``, the JSON it renders, is there."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"--render-only reads {flag} {path}, which does not exist")


def say(prog: str, message: str) -> None:
    """``prog: error: message`` on stderr, the message on one line."""
    print(f"{prog}: error: {' '.join(str(message).split())}", file=sys.stderr)


def parse(args_type: type[A], prog: str, argv: Sequence[str]) -> A:
    """tyro's parse of ``argv``; its error box (an unknown flag, a malformed value) raised as a one-line ValueError,
    ``--help`` and its exit status 0 left alone, and any other text it printed (a warning) passed on to stderr."""
    import tyro

    stderr, held = sys.stderr, io.StringIO()
    sys.stderr = held
    try:
        return tyro.cli(args_type, prog=f"python -m {prog}", args=list(argv))
    except SystemExit as e:
        if e.code in (0, None) or not held.getvalue().strip():
            raise
        from maniskill_irb120.errors import tyro_error_line

        box, held = held.getvalue(), io.StringIO()  # the box becomes the message, not stderr's text as well
        raise ValueError(tyro_error_line(box, f"python -m {prog}")) from None
    finally:
        sys.stderr = stderr
        if held.getvalue():
            stderr.write(held.getvalue())


def entry(
    prog: str,
    args_type: type[A],
    main: Callable[[A], object],
    check: Optional[Callable[[A], None]] = None,
    argv: Optional[Sequence[str]] = None,
    exit_status: bool = False,
) -> object:
    """Parse ``argv`` (default: the command line) into ``args_type``, ``check`` it, then ``main`` it. A bad flag
    (tyro's refusal or ``check``'s ValueError / FileNotFoundError) is one line ``prog: error: ...`` and exit status 2,
    before ``main`` starts; a Ctrl-C is one line and 130. ``exit_status``: ``main`` returns the exit status (an int),
    as ``gpu_acceptance``'s does; otherwise its return value is returned."""
    argv = sys.argv[1:] if argv is None else argv
    try:
        args = parse(args_type, prog, argv)
        if check is not None:
            check(args)
    except INPUT_ERRORS as e:
        say(prog, str(e))
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        raise SystemExit(130) from None
    try:
        result = main(args)
    except KeyboardInterrupt:  # a benchmark that keeps its work on a Ctrl-C has said so and exits 130 itself
        print(f"{prog}: interrupted", file=sys.stderr)
        raise SystemExit(130) from None
    if exit_status:
        raise SystemExit(result)
    return result
