"""benchmarks/results/policies/MANIFEST.json names every committed policy (its recipe, parent, seed, commit and
scores), and the loader takes a policy by its file or by that name."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from maniskill_irb120.sim2real.policy import MANIFEST_ENV, load_policy, resolve_policy

REPO = Path(__file__).resolve().parents[2]
POLICIES = REPO / "benchmarks" / "results" / "policies"
ENTRIES = json.loads((POLICIES / "MANIFEST.json").read_text())["policies"]
TASKS = ("TableClearing-IRB120-v1", "GraspLift-IRB120-v1", "StackCube-IRB120-v1")


def test_manifest_lists_every_committed_policy_once_with_its_fields():
    assert sorted(e["file"] for e in ENTRIES.values()) == sorted(p.name for p in POLICIES.glob("*.pt"))
    for name, e in ENTRIES.items():
        assert re.fullmatch(r"[a-z0-9-]+", name) and len(name) < len(Path(e["file"]).stem), name
        assert e["recipe"] and e["command"] and e["env_id"] in TASKS, name
        assert e["parent"] is None or e["parent"] in ENTRIES, name
        assert isinstance(e["seed"], int) and re.fullmatch(r"[0-9a-f]{40}", e["commit"]), name
        assert isinstance(e["scores"], dict), name
        for row in e["scores"].get("twin", []):
            assert (REPO / row["json"]).is_file() and 0 <= row["twin_success"] <= 1, (name, row)


def test_a_name_resolves_to_its_file_and_a_file_stays_itself(tmp_path, monkeypatch):
    path = resolve_policy("camera-bf16-s1")
    assert Path(path).resolve() == (POLICIES / ENTRIES["camera-bf16-s1"]["file"]).resolve()
    assert resolve_policy(path) == path and resolve_policy("expert") == "expert"
    with pytest.raises(FileNotFoundError, match="nor a name in"):
        resolve_policy("no-such-policy")
    mine = tmp_path / "MANIFEST.json"  # another manifest, by the environment variable
    (tmp_path / "mine.pt").write_bytes(Path(path).read_bytes())
    mine.write_text(json.dumps({"policies": {"mine": {"file": "mine.pt"}}}))
    monkeypatch.setenv(MANIFEST_ENV, str(mine))
    assert resolve_policy("mine") == str(tmp_path / "mine.pt")


def test_the_loader_takes_a_name(monkeypatch):
    monkeypatch.chdir(REPO)
    sim_env, make_policy = load_policy("camera-bf16-s1", "TableClearing-IRB120-v1", "tool_delta")
    try:
        assert callable(make_policy) and "rgb" in sim_env.observation_space.spaces
    finally:
        sim_env.close()
