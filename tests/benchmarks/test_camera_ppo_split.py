"""``benchmarks/camera_ppo_split.py`` runs the camera PPO recipe's pieces at toy sizes, in two configurations side by
side, and writes splits that add up (smoke only: no timing is asserted), refuses bad input in one line, and renders its
section from JSON alone."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[2]
SCRIPT = [sys.executable, "-m", "benchmarks.camera_ppo_split"]


@pytest.mark.slow  # a benchmark's smoke run (~40-80 s on 2 cores), as the other benchmarks' are
def test_quick_run_writes_every_field_and_a_split_that_sums_to_the_total(tmp_path, bench_script):
    out = tmp_path / "c.json"
    run = subprocess.run(
        [*SCRIPT, "--quick", "--configs", "today", "fast", "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    r = json.loads(out.read_text())
    mod = bench_script("camera_ppo_split")
    for key in ("training_env_steps_per_s", "env_only_rgbd_env_steps_per_s", "env_only_state_env_steps_per_s",
                "ratio_training_to_env_only_rgbd", "total_ms_per_env_step", "rendering_ms_per_env_step",
                "wall_min", "command", "versions", "machine", "settings", "rounds"):  # fmt: skip
        assert key in r, key
    assert r["recipe"] == "ppo-rgbd" and r["iterations"] == 1 and r["env_steps"] == r["settings"]["batch_size"]
    assert {"torch_threads_training", "cpus", "loadavg_start", "loadavg_end"} <= set(r["machine"])
    split = r["split_ms_per_env_step"]
    assert set(split) == {key for key, _, _ in mod.PHASES}
    measured = [key for key, _, how in mod.PHASES if how == "measured"]
    assert all(split[key] > 0 for key in measured), split
    assert sum(split.values()) == pytest.approx(r["total_ms_per_env_step"], rel=0.02)
    assert r["ratio_training_to_env_only_rgbd"] == pytest.approx(
        r["training_env_steps_per_s"] / r["env_only_rgbd_env_steps_per_s"]
    )
    assert r["optimizer_steps_per_iteration"] >= 1
    # both configurations, each with its own split and its ratio to the same envs alone
    assert list(r["configs"]) == ["today", "fast"] and list(r["config_rounds"]) == ["fast"]
    from agents.common.precision import native_bf16

    assert r["configs"]["fast"]["precision"] == ("bf16" if native_bf16(torch.device("cpu")) else "fp32")
    assert r["configs"]["today"]["precision"] == "fp32"
    for c in r["configs"].values():
        assert c["env_steps"] == r["env_steps"] and set(c["split_ms_per_env_step"]) == set(split)
        assert sum(c["split_ms_per_env_step"].values()) == pytest.approx(c["total_ms_per_env_step"], rel=0.02)
        assert c["ratio_training_to_env_only_rgbd"] == pytest.approx(
            c["training_env_steps_per_s"] / r["env_only_rgbd_env_steps_per_s"]
        )
        # overlapped, the slower of collection and update sets the pace: never slower than in sequence
        assert c["overlap_bound_env_steps_per_s"] >= c["training_env_steps_per_s"]
    assert r["configs"]["today"]["training_env_steps_per_s"] == r["training_env_steps_per_s"]
    assert "ETA" in run.stderr and "1/1] 32/32 env steps each" in run.stderr  # progress, with the env steps done
    assert "| **total** (1000 / training env steps/s) |" in run.stdout
    # the section renders from this JSON alone, into a copy of the page
    copy = tmp_path / "RESULTS.md"
    shutil.copy(REPO / "benchmarks" / "RESULTS.md", copy)
    mod.update_results(out, copy)
    text = copy.read_text()
    assert text.count(mod.HEAD) == 1 and mod.section(r, out) in text and "The largest phase is" in text


BAD = [
    (["--env-steps", "0"], "--env-steps must be >= 1, got 0"),
    (["--render-only", "--json", "/nonexistent/c.json"], "does not exist"),
    (["--configs", "today", "turbo"], "--configs must name distinct configurations of"),
    (["--configs", "fast", "fast"], "--configs must name distinct configurations of"),
]


@pytest.mark.parametrize("argv, message", BAD)
def test_bad_input_is_one_line_and_exit_code_2(argv, message):
    run = subprocess.run([*SCRIPT, *argv], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and message in run.stderr, run.stderr
    assert "Traceback" not in run.stderr and len(run.stderr.strip().splitlines()) == 1


def test_render_only_measures_nothing(monkeypatch, bench_script):
    mod = bench_script("camera_ppo_split")
    written = []
    monkeypatch.setattr(mod, "update_results", lambda path: written.append(path))
    monkeypatch.setattr(mod, "measure", lambda args: pytest.fail("--render-only measured"))
    report = mod.main(mod.Args(render_only=True))
    assert written == [mod.RESULTS_JSON] and report == json.loads(mod.RESULTS_JSON.read_text())
