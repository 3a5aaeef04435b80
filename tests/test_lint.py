"""The code base stays as ruff (configured in pyproject.toml, pinned in the dev extras) formats and checks it."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
RUFF = shutil.which("ruff", path=str(Path(sys.executable).parent)) or shutil.which("ruff")


@pytest.mark.skipif(RUFF is None, reason="ruff is in the dev extras")
@pytest.mark.parametrize("cmd", [["check", "."], ["format", "--check", "."]])
def test_ruff(cmd):
    out = subprocess.run([RUFF, *cmd], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
