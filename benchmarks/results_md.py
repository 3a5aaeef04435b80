"""The one way a benchmark rewrites its own section of benchmarks/RESULTS.md (hand-written sections stay)."""

from __future__ import annotations

from pathlib import Path


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
