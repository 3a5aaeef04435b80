"""The GPU acceptance suite's own code, on the CPU: the checks ``tests/gpu/`` and ``doctor --gpu`` run on
physx_cuda pass here on physx_cpu (one env, ManiSkill's CPU limit), and each verdict catches the bug it exists
for on hand-made batches (several envs, which the CPU cannot simulate in one process)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from maniskill_irb120.diagnostics import acceptance as A
from maniskill_irb120.diagnostics import acceptance_runs as R
from maniskill_irb120.diagnostics.doctor import format_gpu_report, gpu_report

REPO = Path(__file__).resolve().parents[2]
CPU = "physx_cpu"


# --------------------------------------------------------------------------- the checks pass on the CPU
def test_obs_modes_check_passes_on_cpu():
    ok, why = A.check_obs_modes(CPU, 1, env_ids=A.ENV_IDS[:1])  # every mode on one task
    assert ok, why
    # the other tasks' state and none modes: test_report_side_by_side_...
    ok, why = A.check_obs_modes(CPU, 1, env_ids=A.ENV_IDS[2:], obs_modes=("rgbd",))
    assert ok, why


@pytest.mark.parametrize(
    "name", ["partial resets", "controller targets", "contacts", "rgbd frames", "appearance per env"]
)
def test_env_check_passes_on_cpu(name):
    result = A.timed_check(name, A.ENV_CHECKS[name], sim_backend=CPU, num_envs=1)
    assert result.status == "PASS", result.reason


def test_randomised_frames_check_renders_the_cpu_sims_randomised_frames():
    ok, why = A.check_randomised_frames()
    assert ok, why
    assert "CPU physics, rendered on cpu" in why and A.RANDOMISED_FRAMES in why


# --------------------------------------------------------------------------- the verdicts catch their bugs
def test_obs_problems_name_shape_device_and_nan():
    import gymnasium as gym

    space = gym.spaces.Dict(a=gym.spaces.Box(-1, 1, (3,)), b=gym.spaces.Dict(c=gym.spaces.Box(0, 1, (2, 2))))
    good = dict(a=torch.zeros(4, 3), b=dict(c=torch.zeros(4, 2, 2)))
    assert A.obs_problems(good, space, 4, "cpu") == []
    bad = dict(a=torch.full((4, 3), float("nan")), b=dict(c=torch.zeros(1, 2, 2)))
    found = A.obs_problems(bad, space, 4, "cpu")
    assert any("obs/a: 12 values not finite" in p for p in found) and any(
        "obs/b/c: shape (1, 2, 2)" in p for p in found
    )
    assert A.obs_problems(good, space, 4, "cuda")[0] == "obs/a: on cpu, expected cuda"
    assert A.obs_problems(dict(b=good["b"]), space, 4, "cpu") == ["obs: missing ['a']"]


def _reset_batches(n: int = 4):
    idx = torch.tensor([0, 2])
    start = dict(state=torch.zeros(n, 5), obj=torch.zeros(n, 7), qpos=torch.zeros(n, 3))
    before = dict(state=torch.rand(n, 5), obj=torch.rand(n, 7), qpos=torch.rand(n, 3))
    after = {k: v.clone() for k, v in before.items()}
    after["obj"][idx, :2] = torch.tensor([[0.1, 0.2], [0.3, 0.4]])
    after["qpos"][idx] = 0.0
    return idx, start, before, after


def test_partial_reset_verdict():
    idx, start, before, after = _reset_batches()
    rest = torch.zeros(3)
    assert A.partial_reset_verdict(idx, start, before, after, rest) == (
        True,
        "2 of 4 envs reset to fresh, distinct starts; the other 2 unchanged",
    )
    touched = {k: v.clone() for k, v in after.items()}
    touched["state"][1] += 1
    assert "envs not reset changed state: [1]" in A.partial_reset_verdict(idx, start, before, touched, rest)[1]
    shared = {k: v.clone() for k, v in after.items()}
    shared["obj"][2, :2] = shared["obj"][0, :2]
    assert "same object start" in A.partial_reset_verdict(idx, start, before, shared, rest)[1]
    again = {k: v.clone() for k, v in after.items()}
    again["obj"][2] = start["obj"][2]
    assert "got their first start again" in A.partial_reset_verdict(idx, start, before, again, rest)[1]
    assert "rest pose" in A.partial_reset_verdict(idx, start, before, after, torch.ones(3))[1]


def test_controller_reset_verdict():
    idx = torch.tensor([0, 2])
    measured = dict(q=torch.zeros(4, 6))
    before = dict(q=torch.ones(4, 6))  # every target a step ahead of the robot
    after = dict(q=before["q"].clone())
    after["q"][idx] = 0.0
    assert A.controller_reset_verdict(idx, before, after, measured)[0]
    everyone = dict(q=torch.zeros(4, 6))  # ManiSkill 3.0.1's own controllers: every env's targets reset
    assert (
        "targets of envs not reset were reset too: [1, 3]"
        in A.controller_reset_verdict(idx, before, everyone, measured)[1]
    )
    stale = dict(q=before["q"].clone())
    assert "from their new start" in A.controller_reset_verdict(idx, before, stale, measured)[1]
    idle = dict(q=torch.zeros(4, 6))
    assert "not ahead" in A.controller_reset_verdict(idx, idle, idle, measured)[1]


def test_contact_verdict():
    ref = {0: 24, 6: 30}
    assert A.contact_verdict(ref, (0, 6), [24, 30, 25, 29])[0]
    assert "2 envs never collided" in A.contact_verdict(ref, (0, 6), [24, -1, 24, -1])[1]
    assert "env 1 at step 33, CPU at 30" in A.contact_verdict(ref, (0, 6), [24, 33, 24, 30])[1]
    assert "CPU reference never collided" in A.contact_verdict({0: -1}, (0,), [3])[1]


def test_frames_verdict():
    g = torch.Generator().manual_seed(0)
    rgb = torch.randint(1, 255, (3, 84, 84, 3), generator=g, dtype=torch.uint8)
    depth = torch.randint(1, 500, (3, 84, 84, 1), generator=g, dtype=torch.int16)
    assert A.frames_verdict(rgb, depth, 3)[0]
    shared = rgb.clone()
    shared[2] = shared[0]
    assert "only 2 distinct rgb frames among 3" in A.frames_verdict(shared, depth, 3)[1]
    assert "expected (3, 84, 84, 3/1)" in A.frames_verdict(rgb[:, :64], depth, 3)[1]
    blank = depth.clone()
    blank[1] = 0
    assert "e.g. env 1" in A.frames_verdict(rgb, blank, 3)[1]
    assert "dtype torch.float32" in A.frames_verdict(rgb.float(), depth, 3)[1]


# --------------------------------------------------------------------------- the doctor's report
def test_report_on_cpu_lists_each_check_and_the_steps():
    r = gpu_report(
        CPU,
        num_envs=1,
        trainer_envs=1,
        checks=("controller targets",),
        throughput_envs=(1,),
        throughput_steps=3,
        isolate=False,
    )
    text = format_gpu_report(r)
    assert r["ok"] and json.loads(json.dumps(r)) == r
    assert "  PASS  controller targets " in text and "num_envs=1" in text and "env steps/s" in text
    # the package's report runs no program of a checkout, and says where they are
    assert r["trainer_envs"] is None and "trainers num_envs" not in text
    assert "python -m benchmarks.gpu_acceptance runs this report with them added" in text
    for field in ("device ", "driver ", "CUDA (torch build)", "torch ", "sapien ", "mani-skill ", "commit "):
        assert f"  {field}" in text, field
    assert text.splitlines()[-1] == "VERDICT: PASS - every check passed on physx_cpu"
    r["checks"][0].update(ok=False, status="FAIL", reason="targets of envs not reset were reset too: [1]")
    r["throughput"][0] = dict(num_envs=4096, error="RuntimeError: out of memory")
    r["ok"] = False
    text = format_gpu_report(r)
    assert "  FAIL  controller targets       targets of envs not reset were reset too: [1]" in text
    assert "num_envs=4096   FAIL RuntimeError: out of memory" in text
    assert text.splitlines()[-1] == "VERDICT: FAIL - controller targets, steps/s at 4096"
    with pytest.raises(ValueError, match="unknown checks \\['speed'\\]"):
        gpu_report(CPU, checks=("speed",))


def test_report_side_by_side_splits_the_obs_sweep_into_processes_and_merges_it():
    """--jobs: the sweep's parts run in their own processes beside the other checks and come back as one row"""
    lines: list[str] = []
    r = gpu_report(
        CPU,
        num_envs=1,
        checks=("obs modes", "controller targets"),
        throughput_envs=(),
        jobs=3,
        env_ids=A.ENV_IDS[1:],
        obs_modes=("state",),
        say=lines.append,
    )
    assert r["ok"] and r["jobs"] == 3 and [c["name"] for c in r["checks"]] == ["obs modes", "controller targets"]
    assert r["checks"][0]["reason"].startswith("all 2 parts passed, each in its own process")
    parts = [f"[doctor --gpu] obs modes [{e} state]" for e in A.ENV_IDS[1:]]
    assert sorted(ln.split(":")[0] for ln in lines) == sorted([*parts, "[doctor --gpu] controller targets"])
    with pytest.raises(ValueError, match="jobs=2: expected 1, or more with isolate=True"):
        gpu_report(CPU, jobs=2, isolate=False)
    with pytest.raises(ValueError, match=r"obs_modes=\['rgbd', 'thermal'\]"):
        gpu_report(CPU, obs_modes=("rgbd", "thermal"))


def test_merged_parts_fail_naming_each_failed_part():
    ok = dict(name="a", ok=True, status="PASS", reason="fine", seconds=1.0)
    bad = dict(name="obs modes [X rgb]", ok=False, status="FAIL", reason="obs: 3 values not finite", seconds=2.0)
    skip = dict(name="b", ok=None, status="SKIP", reason="needs CUDA", seconds=0.0)
    m = R.merge_parts("obs modes", [ok, bad, ok], 4.0)
    assert (m["ok"], m["status"], m["seconds"]) == (False, "FAIL", 4.0)
    assert m["reason"] == "1 of 3 parts failed: obs modes [X rgb]: obs: 3 values not finite"
    assert R.merge_parts("x", [skip, skip], 0.0)["status"] == "SKIP"
    assert R.merge_parts("x", [skip, ok], 1.0)["status"] == "PASS"


def _fake_programs(ran: list):
    def ok(sim_backend, num_envs):
        ran.append(("ok", sim_backend, num_envs))
        return True, f"ran on {sim_backend} at {num_envs} envs"

    def crash(sim_backend, num_envs):
        raise RuntimeError("the program exited 134")

    return {"fake ok": ok, "fake crash": crash}


def test_a_checkouts_programs_join_the_report_after_the_packages_checks():
    """benchmarks/gpu_acceptance.py's way in: its programs run at trainer_envs, in report order, an exception is
    their FAIL, and the report names the checkout's commit"""
    ran: list = []
    programs = _fake_programs(ran)
    r = gpu_report(
        CPU,
        num_envs=1,
        trainer_envs=3,
        checks=("fake ok", "fake crash"),
        throughput_envs=(),
        programs=programs,
        commit="abc1234",
    )
    assert ran == [("ok", CPU, 3)] and r["trainer_envs"] == 3 and r["environment"]["commit"] == "abc1234"
    assert [(c["name"], c["status"]) for c in r["checks"]] == [("fake ok", "PASS"), ("fake crash", "FAIL")]
    assert r["checks"][1]["reason"] == "RuntimeError: the program exited 134" and not r["ok"]
    text = format_gpu_report(r)
    assert "trainers num_envs=3" in text and "not run here" not in text and "  commit             abc1234" in text
    with pytest.raises(ValueError, match=r"programs \['contacts'\] have the names of the package's own checks"):
        gpu_report(CPU, programs={"contacts": programs["fake ok"]})
    with pytest.raises(ValueError, match="unknown checks \\['agents.ppo'\\]"):
        gpu_report(CPU, checks=("agents.ppo",))  # the trainers are the checkout's, not the package's


def test_without_physx_gpu_library_the_check_names_the_file_and_the_fix(monkeypatch):
    import sapien

    from maniskill_irb120.maniskill_compat import physx_gpu_library

    assert R.check_physx_gpu(CPU) == (None, "physx_cpu needs no GPU library")

    def offline():
        raise ConnectionError("Failed to resolve 'github.com'")

    monkeypatch.setattr(sapien.physx, "enable_gpu", offline)
    ok, why = R.check_physx_gpu("physx_cuda")
    path, url = physx_gpu_library()
    assert ok is False and str(path) in why and "ConnectionError: Failed to resolve 'github.com'" in why
    assert why.endswith(f"without internet access unzip {url} into {path.parent}")


def test_report_stops_at_a_missing_physx_gpu_library(monkeypatch):
    """one FAIL that says why and the rest SKIP, in seconds, instead of every check failing alike"""
    monkeypatch.setattr(R, "check_physx_gpu", lambda sim_backend: (False, "libPhysXGpu_64.so is missing"))
    ran: list = []
    r = gpu_report(CPU, num_envs=1, throughput_envs=(512,), isolate=False, programs=_fake_programs(ran))
    assert not r["ok"] and [c["name"] for c in r["checks"]] == [*R.CHECK_NAMES, "fake ok", "fake crash"]
    assert ran == []  # a checkout's programs skip too
    status = {c["name"]: c["status"] for c in r["checks"]}
    assert status.pop("physx gpu library") == "FAIL" and status.pop(R.RANDOMISED_FRAMES) == "PASS"  # needs no PhysX GPU
    assert set(status.values()) == {"SKIP"}
    text = format_gpu_report(r)
    assert "FAIL  physx gpu library" in text and "libPhysXGpu_64.so is missing" in text
    assert text.splitlines()[-1] == "VERDICT: FAIL - physx gpu library, steps/s at 512"


def test_what_an_isolated_check_prints_goes_to_stderr(capfd):
    """the doctor's stdout is its report: a child's prints (SAPIEN's download notice) must not land in it"""
    R.isolated("builtins", "print", end="from the child")  # print() with no items writes just its end
    out, err = capfd.readouterr()
    assert "from the child" in err and "from the child" not in out


def test_isolated_reports_a_crash_and_an_exception():
    with pytest.raises(RuntimeError, match=r"_exit crashed \(exit status 3\)"):
        R.isolated("os", "_exit", status=3)
    with pytest.raises(RuntimeError, match="ValueError: unknown check 'nope'"):
        R.isolated(
            "maniskill_irb120.diagnostics.acceptance_runs", "run_named_check", name="nope", sim_backend=CPU, num_envs=1
        )


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on machines without CUDA")
def test_doctor_gpu_without_cuda_says_so_without_a_traceback():
    out = subprocess.run(
        [sys.executable, "-m", "maniskill_irb120.cli", "doctor", "--gpu"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert out.returncode == 2
    assert "doctor --gpu: no CUDA device" in out.stderr and "Traceback" not in out.stdout + out.stderr


def test_appearance_verdict_catches_a_material_shared_across_envs():
    shared = torch.tensor([[0.5, 0.4, 0.3]] * 3)
    ok, why = A.appearance_verdict(shared, torch.ones(3, dtype=torch.bool), 3)
    assert not ok and "shared" in why
    own = torch.tensor([[0.5, 0.4, 0.3], [0.6, 0.4, 0.3], [0.5, 0.2, 0.3]])
    assert not A.appearance_verdict(own, torch.tensor([True, False, True]), 3)[0]
    assert A.appearance_verdict(own, torch.ones(3, dtype=torch.bool), 3)[0]
