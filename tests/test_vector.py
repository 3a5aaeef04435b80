"""The CPU process-vector env behaves like ManiSkillVectorEnv (batched torch, auto-reset, final_info), and under bad
input or after close() it raises clear errors and stays usable where it can."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from gymnasium.vector.async_vector_env import AsyncState

from maniskill_irb120 import vector
from maniskill_irb120.vector import CPUVectorEnv, make_vec_env

ENV = "TableClearing-IRB120-v1"


@pytest.fixture(scope="module")
def venv():
    env = make_vec_env(ENV, 2, backend="cpu", obs_mode="state", max_episode_steps=4)
    yield env
    env.close()


def test_batched_torch_interface(venv):
    obs, info = venv.reset(seed=3)
    assert isinstance(obs, torch.Tensor) and obs.shape[0] == 2
    assert venv.action_space.shape == (2, 5)
    obs, rew, term, trunc, info = venv.step(torch.zeros(2, 5))
    assert rew.shape == (2,) and rew.dtype == torch.float32
    assert term.dtype == torch.bool and trunc.dtype == torch.bool
    assert "success" in info and info["success"].shape == (2,)
    assert info["episode"]["episode_len"].tolist() == [1, 1]


def test_auto_reset_reports_final_info_and_observation(venv):
    venv.reset(seed=5)
    for _ in range(4):  # max_episode_steps=4: the 4th step truncates both envs
        obs, rew, term, trunc, info = venv.step(torch.zeros(2, 5))
    assert trunc.all() or term.all()
    assert info["_final_info"].tolist() == [True, True]
    assert info["final_observation"].shape == obs.shape
    assert not torch.equal(info["final_observation"], obs)  # obs is already the next episode's first
    assert info["final_info"]["episode"]["episode_len"].tolist() == [4, 4]
    assert "success" in info["final_info"]
    # metrics restart with the new episode
    obs, *_, info = venv.step(torch.zeros(2, 5))
    assert info["episode"]["episode_len"].tolist() == [1, 1]


def test_final_observation_of_dict_obs_when_every_env_ends_at_once():
    """rgbd observations are nested dicts; with one worker every episode end is an 'all done' step."""
    env = make_vec_env(ENV, 1, backend="cpu", obs_mode="rgbd", max_episode_steps=2)
    try:
        env.reset(seed=0)
        for _ in range(2):
            obs, rew, term, trunc, info = env.step(torch.zeros(1, 5))
        assert bool(trunc[0] or term[0])
        final = info["final_observation"]
        rgb = final["sensor_data"]["hand_camera"]["rgb"]
        assert rgb.shape == obs["sensor_data"]["hand_camera"]["rgb"].shape == (1, 84, 84, 3)
        assert rgb.dtype == torch.uint8 and final["agent"]["qpos"].dtype == torch.float32
    finally:
        env.close()


def test_partial_reset_only_touches_selected_env(venv):
    venv.reset(seed=7)
    for _ in range(2):
        obs, *_ = venv.step(torch.zeros(2, 5))
    obs2, _ = venv.reset(options=dict(env_idx=torch.tensor([1])))
    assert torch.allclose(obs2[0], obs[0])
    assert not torch.allclose(obs2[1], obs[1])


def test_same_seed_same_initial_state(venv):
    a, _ = venv.reset(seed=11)
    b, _ = venv.reset(seed=11)
    torch.testing.assert_close(a, b)
    assert not torch.allclose(a[0], a[1])  # workers get different seeds (seed + i)


def _assert_same(a, b, where="") -> None:
    """Nested tuples and dicts of tensors/arrays equal, key for key (NaN equal to NaN)."""
    if isinstance(a, tuple):
        assert isinstance(b, tuple) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, dict):
        assert set(a) == set(b), f"{where}: keys {sorted(set(a) ^ set(b))} differ"
        for k in a:
            _assert_same(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, torch.Tensor):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True, msg=lambda m: f"{where}: {m}")
    else:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=where)


def test_env_zero_in_this_process_steps_exactly_as_a_worker():
    """With two envs or more, env 0 runs in the calling process (vector.py says why); everything a step or a reset
    returns -- observations, rewards, flags, infos with their final_info and final_observation at an episode's end,
    partial resets of either side -- is what the same envs return from worker processes."""
    local = make_vec_env(ENV, 2, backend="cpu", obs_mode="state", max_episode_steps=3)
    workers = CPUVectorEnv(ENV, 2, obs_mode="state", max_episode_steps=3, record_metrics=True, local_first=False)
    try:
        assert local.local_first and not workers.local_first
        for env in (local, workers):  # the envs not being reset would have no observation to return
            with pytest.raises(RuntimeError, match="before a first full reset"):
                env.reset(options=dict(env_idx=[1]))
        assert local.observation_space == workers.observation_space
        assert local.action_space == workers.action_space
        _assert_same(local.reset(seed=21), workers.reset(seed=21), "reset")
        gen = torch.Generator().manual_seed(0)
        ends = set()  # which envs ended together: both, env 0 alone, env 1 alone
        for t in range(9):
            action = torch.rand(2, 5, generator=gen) * 2 - 1
            a, b = local.step(action), workers.step(action)
            _assert_same(a, b, f"step {t}")
            if "final_info" in a[4]:
                ends.add(tuple(a[4]["_final_info"].tolist()))
            if t in (3, 5):  # partial resets of env 0 (this process), then of env 1 (the worker), out of step
                idx = [0] if t == 3 else [1]
                _assert_same(local.reset(options=dict(env_idx=idx)), workers.reset(options=dict(env_idx=idx)), f"r{t}")
        assert ends == {(True, True), (False, True), (True, False)}  # every autoreset path ran
        assert local.call("elapsed_steps") == workers.call("elapsed_steps")
        with pytest.raises(ValueError, match="use `step` directly"):
            local.call("step", None)
    finally:
        local.close()
        workers.close()


def test_bad_inputs(venv):
    with pytest.raises(ValueError, match="shape"):
        venv.step(torch.zeros(3, 5))
    with pytest.raises(ValueError, match="backend"):
        make_vec_env(ENV, 2, backend="tpu")
    with pytest.raises(ValueError, match="CUDA"):
        if not torch.cuda.is_available():
            make_vec_env(ENV, 2, backend="gpu")
        else:
            raise ValueError("CUDA present: nothing to check")


def test_on_host_partial_reset_takes_host_indices():
    """Trainers hand OnHost host-side indices (lists, numpy); ManiSkill indexes its device buffers with
    env_idx as given, so OnHost must pass it on as a tensor on the env's device."""
    import gymnasium as gym
    import numpy as np

    from maniskill_irb120.vector import OnHost

    class Spy(gym.vector.VectorWrapper):
        def __init__(self, env):
            super().__init__(env)
            self.seen: list = []

        def reset(self, *, seed=None, options=None):
            self.seen.append((options or {}).get("env_idx"))
            return self.env.reset(seed=seed, options=options)

    inner = make_vec_env(ENV, 1, backend="inprocess", obs_mode="state", max_episode_steps=4)
    spy = Spy(inner)
    env = OnHost(spy)
    try:
        assert env.env_device == torch.device(inner.device)  # read through the wrapper, from the base env
        first, _ = env.reset(seed=21)
        for _ in range(2):
            moved, *_ = env.step(torch.ones(1, 5))
        assert not torch.allclose(moved, first)
        for idx in ([0], np.array([0])):
            again, _ = env.reset(seed=21, options=dict(env_idx=idx))
            got = spy.seen[-1]
            assert isinstance(got, torch.Tensor) and got.device == torch.device(inner.device)
            assert again.device.type == "cpu"
            torch.testing.assert_close(again, first)
    finally:
        env.close()


def test_make_vec_env_sim_backend_keyword():
    envs = make_vec_env(ENV, 1, backend="inprocess", sim_backend="physx_cpu", obs_mode="state")
    envs.reset(seed=0)
    envs.close()
    with pytest.raises(ValueError, match="sim_backend='physx_cuda'"):
        make_vec_env(ENV, 1, backend="inprocess", sim_backend="physx_cuda")
    with pytest.raises(ValueError, match="runs physx_cuda"):
        make_vec_env(ENV, 4, backend="gpu", sim_backend="physx_cpu")


# ------------------------------------------------------- bad input: the vector env stays usable after a rejected call
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_vector_env_rejects_non_finite_action_and_stays_usable(venv, bad):
    venv.reset(seed=0)
    actions = torch.zeros(2, 5)
    actions[1, 2] = bad
    with pytest.raises(ValueError, match=r"NaN or inf for env index \[1\]"):
        venv.step(actions)
    obs, rew, term, trunc, info = venv.step(torch.zeros(2, 5))  # the workers are alive
    assert obs.shape[0] == 2 and torch.isfinite(rew).all()


@pytest.mark.parametrize(
    "bad,err,match",
    [
        ("left", TypeError, "str"),
        ([["a"] * 5] * 2, TypeError, "dtype"),
        (np.zeros((2, 5), dtype=object), TypeError, "dtype object"),
        (np.zeros((2, 5), dtype=bool), TypeError, "dtype bool"),
        (torch.zeros(2, 5, dtype=torch.complex64), TypeError, "complex"),
        ({"action": 0}, TypeError, "dict"),
        ([[0.0] * 5, [0.0] * 4], ValueError, "rectangular"),
        (np.zeros((2, 4)), ValueError, "shape"),
    ],
)
def test_vector_env_rejects_wrong_types_and_stays_usable(venv, bad, err, match):
    venv.reset(seed=0)
    with pytest.raises(err, match=match):
        venv.step(bad)
    venv.step(np.zeros((2, 5), dtype=np.int64))  # integers are numbers; the workers are alive


def test_vector_env_reset_env_idx_checked_and_stays_usable(venv):
    venv.reset(seed=0)
    with pytest.raises(ValueError, match=r"\[2\] out of range: valid env indices are 0\.\.1"):
        venv.reset(options={"env_idx": [2]})
    with pytest.raises(ValueError, match="repeats"):
        venv.reset(options={"env_idx": [1, 1]})
    obs, _ = venv.reset(options={"env_idx": torch.tensor([1])})
    assert obs.shape[0] == 2
    venv.step(torch.zeros(2, 5))


# --------------------------------------------------------------------------- after close() or a dead worker
def test_vector_env_after_close_raises_clear_error():
    v = make_vec_env(ENV, 1, backend="cpu", obs_mode="state")
    v.reset(seed=0)
    v.close()
    for call in (lambda: v.step(torch.zeros(1, 5)), lambda: v.reset(seed=0), v.render):
        with pytest.raises(RuntimeError, match="the vector env is closed"):
            call()
    v.close()


def test_vector_env_close_after_an_interrupted_step_returns(monkeypatch):
    """A Ctrl-C inside gymnasium's step_wait, after it read one worker's result and before the next, leaves the
    step half-read; gymnasium's close without a timeout then waits on the read pipe forever. Ours waits its
    timeout, terminates the workers and returns."""
    monkeypatch.setattr(vector, "CLOSE_TIMEOUT_S", 1.0)
    v = make_vec_env(ENV, 3, backend="cpu", obs_mode="state")
    v.reset(seed=0)
    inner = v._venv
    inner.step_async(np.zeros((2, 5), dtype=np.float32))
    inner.parent_pipes[0].recv()  # the first worker's result read, then the interrupt
    processes = list(inner.processes)
    closer = threading.Thread(target=v.close, daemon=True)
    started = time.perf_counter()
    closer.start()
    closer.join(timeout=60)
    assert not closer.is_alive(), "close() did not return"
    assert time.perf_counter() - started < 30
    assert not any(p.is_alive() for p in processes)
    with pytest.raises(RuntimeError, match="the vector env is closed"):
        v.step(torch.zeros(3, 5))


class _InterruptAfterSend:
    """A worker pipe whose ``send`` delivers a Ctrl-C (or ``signum``) to this process once the command is out: the
    moment gymnasium has sent "step" and not yet recorded that a reply is due."""

    def __init__(self, pipe, signum=signal.SIGINT):
        self.pipe, self.signum = pipe, signum

    def send(self, obj):
        self.pipe.send(obj)
        if obj[0] == "step":
            signal.raise_signal(self.signum)

    def __getattr__(self, name):
        return getattr(self.pipe, name)


def test_a_ctrl_c_as_a_step_is_sent_leaves_the_workers_to_close_cleanly():
    """Without the Ctrl-C held over gymnasium's pipe calls, close() read the step's reply as the answer to its
    "close", shut the pipe, and the worker died on a BrokenPipeError traceback (exit status 1, and the traceback on
    the user's terminal). Held, the interrupt arrives after the step is recorded as in flight: close() collects it,
    and every worker exits cleanly."""
    # Ctrl-C as at a terminal, even where pytest itself was started as a background job (``cmd &`` in a script),
    # which inherits SIGINT ignored
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:  # the handler is put back even when the env fails to build
        v = make_vec_env(ENV, 2, backend="cpu", obs_mode="state")
        inner = v._venv
        try:
            v.reset(seed=0)
            real = inner.parent_pipes[0]
            inner.parent_pipes[0] = _InterruptAfterSend(real)
            with pytest.raises(KeyboardInterrupt):
                v.step(torch.zeros(2, 5))
            inner.parent_pipes[0] = real
            assert inner._state is AsyncState.DEFAULT  # the step in flight was collected: nothing left for close()
            assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is back
        finally:
            processes = list(inner.processes)
            v.close()
    finally:
        signal.signal(signal.SIGINT, before)
    assert [p.exitcode for p in processes] == [0]


def test_a_sigterm_as_a_step_is_sent_is_held_too_where_sigint_is_ignored():
    """A run started in the background by a script (``cmd &``) inherits SIGINT ignored, so a SIGTERM, which
    terminate_as_interrupt turns into a Ctrl-C, cannot go through SIGINT's handler: it raises KeyboardInterrupt
    itself, and the pipe call holds it as it holds a Ctrl-C. Before, such a run ignored SIGTERM altogether."""
    from maniskill_irb120.errors import terminate_as_interrupt

    v = make_vec_env(ENV, 2, backend="cpu", obs_mode="state")
    inner = v._venv
    before, term_before = signal.signal(signal.SIGINT, signal.SIG_IGN), signal.getsignal(signal.SIGTERM)
    try:
        v.reset(seed=0)
        real = inner.parent_pipes[0]
        inner.parent_pipes[0] = _InterruptAfterSend(real, signal.SIGTERM)
        with terminate_as_interrupt():
            held_term = signal.getsignal(signal.SIGTERM)
            with pytest.raises(KeyboardInterrupt):
                v.step(torch.zeros(2, 5))
            assert signal.getsignal(signal.SIGTERM) is held_term  # the pipe call put terminate_as_interrupt's back
        inner.parent_pipes[0] = real
        assert inner._state is AsyncState.DEFAULT  # held until the step was recorded in flight, then collected:
        assert not real.poll(1.0)  # no reply is left unread for close() to take as the answer to its "close"
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        assert signal.getsignal(signal.SIGTERM) is term_before  # and terminate_as_interrupt's exit its own
    finally:
        signal.signal(signal.SIGINT, before)
        processes = list(inner.processes)
        v.close()
    assert [p.exitcode for p in processes] == [0]


def test_vector_env_after_a_worker_died_says_so():
    """An error inside a worker (here an unknown attribute through call()) makes gymnasium shut that worker down;
    later calls say so instead of failing with 'NoneType' object has no attribute 'send'."""
    v = make_vec_env(ENV, 1, backend="cpu", obs_mode="state")
    try:
        v.reset(seed=0)
        with pytest.raises(RuntimeError, match="render_mode is not set"):  # checked before dispatch: no harm
            v.render()
        v.step(torch.zeros(1, 5))
        with pytest.raises(AttributeError, match="no_such_method"):
            v.call("no_such_method")
        with pytest.raises(RuntimeError, match=r"worker\(s\) \[0\] of this vector env were shut down"):
            v.step(torch.zeros(1, 5))
    finally:
        v.close()


# --------------------------------------------------------------------------- README snippet
def test_readme_vec_env_snippet_runs_as_a_script(tmp_path, readme_snippet):
    """The README's make_vec_env snippet saved as a script and run: the CPU workers re-import the main
    module (forkserver), which only works under the ``if __name__ == "__main__":`` guard."""
    script = tmp_path / "vec_env_snippet.py"
    script.write_text(readme_snippet("vec-env"))
    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)}
    out = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "(2, 84, 84, 3) (2,)" in out.stdout, out.stdout


def test_building_the_workers_leaves_this_process_threads_alone(monkeypatch):
    """Gymnasium builds one env in the calling process to read the spaces, which ran the workers' one-thread setup
    here too: the learner beside the workers then trained on one torch thread."""
    monkeypatch.delenv("LP_NUM_THREADS", raising=False)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        env = make_vec_env(ENV, 1, backend="cpu", obs_mode="state", max_episode_steps=4)
        env.close()
        assert torch.get_num_threads() == 2 and "LP_NUM_THREADS" not in os.environ
    finally:
        torch.set_num_threads(before)
