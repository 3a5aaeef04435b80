"""Every python block of README.md runs as written, in a fresh interpreter (blocks with a marker naming
another test are run, with more checks, there)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

README = (Path(__file__).resolve().parents[1] / "README.md").read_text()
BLOCKS = re.findall(
    r"(<!-- README snippet \"[^\"]+\" \(run [^)]*?tests/([\w/]+)\.py\) -->\s*)?```python\n(.*?)```", README, re.S
)
OURS = [code for _, test, code in BLOCKS if test in ("", "test_readme")]


def test_every_block_is_run_somewhere():
    others = {test for _, test, _ in BLOCKS if test not in ("", "test_readme")}
    for test in others:
        assert (Path(__file__).parent / f"{test}.py").exists(), test
    assert len(OURS) >= 2


@pytest.mark.parametrize("code", OURS, ids=[c.splitlines()[0][:40] for c in OURS])
def test_block_runs(code, tmp_path):
    script = tmp_path / "snippet.py"
    script.write_text(code)
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
