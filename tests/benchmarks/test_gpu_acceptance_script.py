"""``benchmarks/gpu_acceptance.py``, the checkout's GPU acceptance report, on the CPU: its trainer and benchmark
command lines parse with the programs' own arguments, its verdicts read the programs' output, PPO's tiny run
passes on the CPU backend, and its programs join the doctor's report."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest
import tyro

from maniskill_irb120.diagnostics.doctor import format_gpu_report, gpu_report

REPO = Path(__file__).resolve().parents[2]
CPU = "physx_cpu"


@pytest.fixture(scope="module")
def G(bench_script):
    """benchmarks/gpu_acceptance.py, loaded once for this file."""
    return bench_script("gpu_acceptance")


# --------------------------------------------------------------------------- the programs' command lines
def test_trainer_commands_parse_with_the_trainers_own_args(G, gpu_trainer, tmp_path):
    trainer = gpu_trainer  # each of G.TRAINERS in turn (conftest.py parametrizes it)
    cmd = G.trainer_command(trainer, "physx_cuda", 64, tmp_path, obs="state")
    assert cmd[:3] == [sys.executable, "-m", f"agents.{trainer}"]
    module = importlib.import_module(f"agents.{trainer}")
    args = tyro.cli(module.Args, args=cmd[3:])
    assert (args.backend, args.num_envs, args.runs_dir, args.progress) == ("gpu", 64, tmp_path, False)
    if trainer == "ppo":
        assert args.total_env_steps // args.batch_size == 2
        assert args.state_net == "mlp" and args.obs_norm  # the from-the-reward recipe's network, on the GPU
    with pytest.raises(ValueError, match="unknown trainer 'td3'"):
        G.trainer_command("td3", "physx_cuda", 1, tmp_path)


def test_the_camera_recipe_is_a_check_of_its_own(G, tmp_path):
    assert G.PROGRAMS[G.CAMERA_DAGGER] is G.check_camera_dagger
    cmd = G.trainer_command("dagger", "physx_cuda", G.CAMERA_DAGGER_ENVS, tmp_path, obs="rgbd")
    args = tyro.cli(importlib.import_module("agents.dagger").Args, args=cmd[3:])
    assert (args.obs, args.encoder, args.precision, args.num_envs) == ("rgbd", "keypoints", "auto", 8)


def test_benchmark_command_parses_with_the_benchmarks_args(G, tmp_path, bench_script):
    cmd = G.benchmark_command(tmp_path / "g.json")
    assert cmd[1:3] == ["-m", "benchmarks.sim_speed"] and (REPO / "benchmarks" / "sim_speed.py").is_file()
    sim_speed = bench_script("sim_speed")
    args = tyro.cli(sim_speed.Args, args=cmd[3:])
    assert args.gpu_only and args.gpu_num_envs == G.BENCH_ENVS and args.json == tmp_path / "g.json"


# --------------------------------------------------------------------------- the verdicts
def test_program_verdicts(G):
    assert G.trainer_verdict("ppo", 0, dict(iterations=2, env_steps=32, wall_clock_s=1.0), "")[0]
    assert G.trainer_verdict("ppo", 0, dict(iterations=1), "") == (False, "iterations=1, expected >= 2")
    assert G.trainer_verdict("dagger", 1, None, "x\nRuntimeError: boom\n") == (
        False,
        "exit status 1: RuntimeError: boom",
    )
    assert "no result JSON" in G.trainer_verdict("sac", 0, None, "tqdm line")[1]
    rows = [dict(num_envs=n, env_steps_per_s=100.0) for n in G.BENCH_ENVS]
    assert G.benchmark_verdict(0, dict(gpu_scaling=rows), "")[0]
    assert "expected (16, 64)" in G.benchmark_verdict(0, dict(gpu_scaling=rows[:1]), "")[1]
    assert G.benchmark_verdict(1, None, "SystemExit: --gpu-only needs CUDA")[1].endswith("needs CUDA")


# --------------------------------------------------------------------------- the runs, and the report
def test_ppo_check_runs_the_trainer_on_cpu(G):
    ok, why = G.check_trainer("ppo", CPU, 1, obs="state")
    assert ok, why
    assert why.startswith("iterations=2")


def test_its_programs_join_the_doctors_report_after_the_packages_checks(G):
    r = gpu_report(
        CPU,
        num_envs=1,
        trainer_envs=1,
        checks=(G.BENCHMARK,),
        throughput_envs=(),
        isolate=False,
        programs=G.PROGRAMS,
        commit=G.git_commit(),
    )
    assert list(G.PROGRAMS) == ["agents.ppo", "agents.sac", "agents.dagger", G.CAMERA_DAGGER, G.BENCHMARK]
    assert r["ok"] and r["trainer_envs"] == 1 and r["environment"]["commit"] == G.git_commit()
    text = format_gpu_report(r)
    assert "  SKIP  sim_speed.py --gpu-only  the GPU sweep needs physx_cuda" in text
    assert "trainers num_envs=1" in text and "not run here" not in text


def test_commit_and_bad_input(G, tmp_path):
    assert G.git_commit() and G.git_commit(tmp_path) is None
    for flags, message in ((dict(jobs=0), "--jobs 0: expected 1 or more"), (dict(trainer_envs=0), "--trainer-envs 0")):
        with pytest.raises(ValueError, match=message):
            G.main(G.Args(**flags))
