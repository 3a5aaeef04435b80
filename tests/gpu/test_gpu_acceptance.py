"""The GPU acceptance suite (``pytest -m gpu`` on a machine with CUDA; skipped, and counted, without one).

The GPU path has not run before its first GPU: these tests make that first run a verdict. Each calls the check
that ``maniskill-irb120 doctor --gpu`` reports (``maniskill_irb120/diagnostics/acceptance*.py``), and the
trainers' and the benchmark's runs that ``benchmarks/gpu_acceptance.py`` adds, on ``physx_cuda`` with 512 envs;
``tests/diagnostics/test_acceptance.py`` and ``tests/benchmarks/test_gpu_acceptance_script.py`` run the same
functions on the CPU, so a failure here is the GPU path's.
"""

from __future__ import annotations

import importlib.util

import pytest
import torch

from maniskill_irb120.diagnostics import acceptance as A
from maniskill_irb120.diagnostics import acceptance_runs as R

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(
        not torch.cuda.is_available(), reason="GPU acceptance suite: needs CUDA (on a GPU machine: pytest -m gpu)"
    ),
]

GPU = "physx_cuda"
NUM_ENVS = 512
TRAINER_ENVS = 64


def checkout_script():
    """benchmarks.gpu_acceptance (the checkout's programs: the trainers, the benchmark) as a module."""
    return importlib.import_module("benchmarks.gpu_acceptance")


@pytest.mark.parametrize("obs_mode", A.OBS_MODES)
@pytest.mark.parametrize("env_id", A.ENV_IDS)
def test_every_task_and_obs_mode_resets_and_steps_batched(env_id, obs_mode):
    ok, why = A.check_obs_modes(GPU, NUM_ENVS, env_ids=[env_id], obs_modes=[obs_mode])
    assert ok, why


@pytest.mark.parametrize("name", [n for n in A.ENV_CHECKS if n != "obs modes"])
def test_env_check_passes_batched_on_the_gpu(name):
    """partial resets give fresh per-env starts; controller targets reset per env; the batched contact query
    agrees with the CPU scan; batched RGB-D frames have the policy's shape and differ per env; appearance
    randomisation gives each env its own materials"""
    ok, why = A.ENV_CHECKS[name](sim_backend=GPU, num_envs=NUM_ENVS)
    assert ok, why


def test_the_cpu_sims_randomised_frames_render_on_the_gpu():
    """CPU physics, CUDA rendering, the depth model and noise drawn on the CPU (needs no PhysX GPU library)"""
    result = R.run_named_check(R.RANDOMISED_FRAMES, GPU, NUM_ENVS)
    assert result["status"] == "PASS" and "rendered on cuda" in result["reason"], result["reason"]


@pytest.mark.parametrize("trainer", ("ppo", "sac", "dagger"))
def test_trainer_runs_its_tiny_loop_on_the_gpu(trainer):
    ok, why = checkout_script().check_trainer(trainer, GPU, TRAINER_ENVS)
    assert ok, why


def test_the_camera_dagger_recipe_runs_a_round_on_the_gpu():
    """rgbd, the keypoint encoder, the auxiliary head and --precision auto (fp32 on a GPU)"""
    ok, why = checkout_script().check_camera_dagger(GPU, TRAINER_ENVS)
    assert ok, why


def test_sim_speed_gpu_only_smoke():
    ok, why = checkout_script().check_benchmark(GPU)
    assert ok, why


def test_doctor_gpu_report_runs_its_checks_in_fresh_processes():
    from maniskill_irb120.diagnostics.doctor import format_gpu_report, gpu_report

    r = gpu_report(checks=("rgbd frames",), throughput_envs=(NUM_ENVS,), throughput_steps=10)
    text = format_gpu_report(r)
    assert r["ok"], text
    assert r["environment"]["device"] and "PASS  rgbd frames" in text
