"""The one way a benchmark rewrites its own section of benchmarks/RESULTS.md (hand-written sections stay).

A benchmark renders its section from its JSON alone, so the page shows exactly what the JSON says: after a run
(``--update-results``) and again from the committed JSON without measuring anything (``--render-only``), and a
test renders it once more and compares it with the page. The plots' smoothing is here too.
"""

from __future__ import annotations

import shlex
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "RESULTS.md"


def replace_section(results: Path, head: str, section: str) -> None:
    """Replace the section that starts with ``head`` (up to the next ``## ``) by ``section``; append if absent."""
    text = results.read_text()
    start = text.find(head)
    if start < 0:
        text = text.rstrip() + "\n\n" + section
    else:
        end = text.find("\n## ", start + len(head))
        text = text[:start] + section + (text[end + 1 :] if end >= 0 else "")
    results.write_text(text)


def read_section(results: Path, head: str) -> str | None:
    """The section that starts with ``head``, as ``replace_section`` would replace it (None if absent)."""
    text = results.read_text()
    start = text.find(head)
    if start < 0:
        return None
    end = text.find("\n## ", start + len(head))
    return text[start : end + 1 if end >= 0 else len(text)]


def linked_path(path: Path | str) -> str:
    """Where a section links a file: relative to RESULTS.md where it lies inside the repository, else as it lies."""
    path = Path(path)
    path = (path if path.is_absolute() else ROOT / path).resolve()
    try:
        return path.relative_to((ROOT / "benchmarks").resolve()).as_posix()
    except ValueError:  # a JSON written outside the repository is linked where it lies
        return path.as_posix()


def raw_link(path: Path | str) -> str:
    """A markdown link to a file the section shows (:func:`linked_path`)."""
    rel = linked_path(path)
    return f"[`{rel}`]({rel})"


def recorded_command(command: str) -> str:
    """A JSON's recorded command as it is typed: scripts that stored ``sys.argv`` joined start at the script."""
    return command if command.split(" ", 1)[0].endswith(("python", "python3")) else f"python {command}"


def argv_command(module: str, argv: list[str]) -> str:
    """The command to store in a benchmark's JSON (``module`` run with ``-m`` from the repository root): quoted as a
    shell reads it, so the page's copy runs as shown."""
    return "python -m " + shlex.join([module, *argv])


def smoothed(values: list[float], points: int = 60) -> np.ndarray:
    """A trailing mean over ~1/``points`` of the curve: PPO logs a point per handful of episodes (each 0 or 1),
    which drawn raw fills the plot with a solid band."""
    v = np.asarray(values, dtype=float)
    w = max(1, len(v) // points)
    return np.array([v[max(0, i - w + 1) : i + 1].mean() for i in range(len(v))])
