"""``maniskill-irb120 --help`` is a short list, one line per command that fits a terminal, and each command's own
``--help`` is plain text (no RST ``literal`` marks) with a help line for every flag; a misspelt command is answered
in one line with the nearest one. In-process: tyro's parser, no env is built."""

from __future__ import annotations

import contextlib
import inspect
import io
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from maniskill_irb120.cli import COMMANDS, main


def run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as e:  # tyro exits after a subcommand's help
            code = e.code
    return code, out.getvalue(), err.getvalue()


def test_top_level_help_is_one_line_per_command(monkeypatch):
    code, out, _ = run(["--help"])
    lines = out.splitlines()
    assert code == 0 and len(lines) <= len(COMMANDS) + 8, out
    assert all(len(line) <= 80 for line in lines), [line for line in lines if len(line) > 80]
    for name in COMMANDS:
        assert sum(line.split()[:1] == [name] for line in lines) == 1, name
    assert "``" not in out


@pytest.mark.parametrize("name", list(COMMANDS))
def test_a_commands_help_is_plain_text_with_every_flag_explained(name, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")  # one row a flag
    code, out, _ = run([name, "--help"])
    assert code == 0 and f"usage: maniskill-irb120 {name}" in out, out
    assert "``" not in out, out
    positional, options = out.split("--help")[-2:]  # the options table, after -h's own row; the positionals before
    for param in inspect.signature(COMMANDS[name]).parameters:
        flag = "--" + param.replace("_", "-")
        if param == "action":  # deploy's positional: its choices, then its help
            row = re.search(r"\[\{load,status,start,stop,unload\}\](.*?)\(default", positional, re.S)
            assert row and len(row.group(1).split()) >= 5, positional
            continue
        row = re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])(.*?)\((default|required)", options, re.S)
        assert row, (flag, options)
        # what stands between the flag and tyro's "(default: ...)": its metavar, its --no- form and its help
        words = [w for w in re.sub(r"[│╭╮╰╯─]", " ", row.group(1)).split() if not w.startswith("--")]
        assert len([w for w in words if not w.isupper() and w not in ("{None}|STR", "|")]) >= 2, (flag, row.group(0))


def test_a_misspelt_command_is_one_line_with_the_nearest():
    code, out, err = run(["exper", "--episodes", "3"])
    assert code == 2 and out == "" and len(err.splitlines()) == 1, err
    assert "no command 'exper' (did you mean 'expert'?)" in err and "sim2real-eval" in err


def test_help_into_a_closed_pipe_ends_quietly(tmp_path):
    """``maniskill-irb120 sim2real-eval --help | head -3``: the reader is gone before the help is written."""
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    p = subprocess.Popen(
        [sys.executable, "-m", "maniskill_irb120.cli", "sim2real-eval", "--help"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
    )
    p.stdout.close()
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 0 and err == "", err[-2000:]
