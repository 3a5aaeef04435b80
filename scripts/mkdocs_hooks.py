"""MkDocs hooks (``mkdocs.yml``): pages made at build time, so they cannot go stale.

* ``cli.md``: ``maniskill-irb120 --help`` and every subcommand's ``--help``, as tyro prints them.
* ``results.md``: ``benchmarks/RESULTS.md`` with its links made relative to the site, and the plots and JSON it
  links (``benchmarks/results/``) beside it; a link to that folder goes to the page's list of them (``#files``),
  since a folder of a static site has no page of its own.

Nothing is fetched from the network.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
from pathlib import Path

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[1]
WIDTH = "80"  # the width of the page's code column


def _help(argv: list[str]) -> str:
    """What ``maniskill-irb120 ARGV`` prints (tyro exits after a subcommand's help)."""
    from maniskill_irb120.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
        main(argv)
    return out.getvalue().rstrip()


def cli_page() -> str:
    """The CLI reference page, from ``--help`` (the docstrings of ``maniskill_irb120/cli.py``)."""
    os.environ["COLUMNS"] = WIDTH
    os.environ["NO_COLOR"] = "1"
    from maniskill_irb120.cli import COMMANDS

    parts = [
        "# Command line: `maniskill-irb120`",
        "",
        "Generated at build time from `maniskill-irb120 --help` and each subcommand's `--help` "
        "(`python -m maniskill_irb120` is the same command).",
        "",
        "```text",
        _help(["--help"]),
        "```",
    ]
    for name in COMMANDS:
        parts += ["", f"## `maniskill-irb120 {name}`", "", "```text", _help([name, "--help"]), "```"]
    return "\n".join(parts) + "\n"


RESULTS = ROOT / "benchmarks" / "results"
FILES_ANCHOR = "files"
"""the results page's list of the files under ``benchmarks/results/`` the site carries"""


def site_files() -> list[Path]:
    """The JSON and plots of ``benchmarks/results/`` the site carries (its checkpoints stay in the repository)."""
    return [p for p in sorted(RESULTS.rglob("*")) if p.suffix in (".png", ".json") and p.is_file()]


LINK = re.compile(r"(!?)\[([^\]]*)\]\(([^)\s]+)\)")


def site_links(text: str, source_dir: Path, page_uri: str) -> str:
    """Links that are right in the repository (relative to ``source_dir``) made right on the site: the results
    page and its files move to ``results.md`` and ``results/``; other files outside ``docs/`` become their path."""
    page_dir = Path(page_uri).parent

    def fix(m: re.Match) -> str:
        bang, label, target = m.groups()
        if re.match(r"[a-z]+:|#", target):
            return m.group(0)
        path, _, anchor = target.partition("#")
        dest = (source_dir / path).resolve()
        if dest == RESULTS:
            site, anchor = Path("results.md"), FILES_ANCHOR
        elif dest.is_relative_to(ROOT / "docs"):
            site = dest.relative_to(ROOT / "docs")
        elif dest == ROOT / "benchmarks" / "RESULTS.md":
            site = Path("results.md")
        elif dest.is_relative_to(RESULTS):
            site = Path("results") / dest.relative_to(RESULTS)
        else:
            return f"{label} (`{dest.relative_to(ROOT).as_posix()}`)" if dest.is_relative_to(ROOT) else m.group(0)
        rel = os.path.relpath(site, page_dir).replace(os.sep, "/")
        return f"{bang}[{label}]({rel}{'#' + anchor if anchor else ''})"

    return LINK.sub(fix, text)


def results_page() -> str:
    """``benchmarks/RESULTS.md`` as the site's ``results.md``, ending in the list of the files it draws on."""
    page = site_links((ROOT / "benchmarks" / "RESULTS.md").read_text(), ROOT / "benchmarks", "results.md")
    listed = [
        f"- [`{p.relative_to(RESULTS).as_posix()}`](results/{p.relative_to(RESULTS).as_posix()})" for p in site_files()
    ]
    return (
        page.rstrip()
        + f"\n\n## Files {{#{FILES_ANCHOR}}}\n\nThe JSON and the plots of `benchmarks/results/`:\n\n"
        + "\n".join(listed)
        + "\n"
    )


def on_page_markdown(markdown: str, page, config, files) -> str:
    if page.file.src_uri in ("results.md", "cli.md"):
        return markdown
    return site_links(markdown, (ROOT / "docs" / page.file.src_uri).parent, page.file.src_uri)


def on_files(files: Files, config) -> Files:
    files.append(File.generated(config, "cli.md", content=cli_page()))
    files.append(File.generated(config, "results.md", content=results_page()))
    for path in site_files():
        uri = "results/" + path.relative_to(RESULTS).as_posix()
        files.append(File.generated(config, uri, abs_src_path=str(path)))
    return files
