"""PPO's ``--overlap``: the next rollout collected in a thread while the update runs. Its env steps count once, as
a run without it counts them; the log-probabilities it stores are those of the weights that acted (one update
behind the learner); a save and ``--resume`` lose and double-count nothing; a command line it cannot run is one
line."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import torch

import agents.ppo as ppo
from agents.ppo import Args, main
from maniskill_irb120.vector import CPUVectorEnv

TINY = dict(
    obs="state",
    state_net="mlp",
    env_id="GraspLift-IRB120-v1",
    num_envs=2,
    num_steps=8,
    num_minibatches=2,
    update_epochs=2,
    eval_freq=0,
    eval_episodes=0,
    save_freq=100,
    exp_name="t",
    progress=False,
)


def run(tmp_path: Path, **kw) -> dict:
    return main(Args(**{**TINY, "runs_dir": tmp_path, **kw}))


@pytest.fixture
def stepped(monkeypatch):
    """The env steps the training envs take, counted where they are taken (one per env of every batched step)."""
    count = [0]
    step = CPUVectorEnv.step

    def counted(self, actions):
        count[0] += self.num_envs
        return step(self, actions)

    monkeypatch.setattr(CPUVectorEnv, "step", counted)
    return count


def test_an_overlapped_run_steps_and_counts_the_env_steps_a_sequential_run_does(tmp_path, stepped):
    """Same budget, same counters, and no env step taken that is not trained on: the last iteration collects
    nothing ahead; the running normaliser sees each rollout once."""
    plain = run(tmp_path / "plain", total_env_steps=40)
    plain_steps, stepped[0] = stepped[0], 0
    over = run(tmp_path / "over", total_env_steps=40, overlap=True, obs_norm=True)
    assert (plain["env_steps"], plain["iterations"]) == (over["env_steps"], over["iterations"]) == (48, 3)
    assert plain_steps == stepped[0] == 48
    saved = torch.load(over["checkpoint"], weights_only=False)
    assert saved["counters"]["env_steps"] == 48 and float(saved["model"]["norm.count"]) == 48


def test_two_overlapped_runs_of_one_seed_end_on_the_same_weights(tmp_path):
    """The collector draws its actions from a generator of its own: how the two threads interleave changes
    nothing."""
    a, b = (run(tmp_path / name, total_env_steps=32, overlap=True) for name in ("a", "b"))
    a, b = (torch.load(r["checkpoint"], weights_only=False)["model"] for r in (a, b))
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_the_stored_log_probs_are_the_acting_snapshots_one_update_behind(tmp_path, monkeypatch):
    """Every rollout's stored log-probabilities and values are those of the weights that collected it (recomputed
    with a copy of them), and the rollout trained on in update k was collected by the learner's weights from before
    update k-1: one update behind (the first by the weights it starts from)."""
    collected, updated = [], []
    collect, update = ppo.Rollout.collect, ppo.ppo_update

    def recording_collect(self, agent, *a, **kw):
        snapshot = copy.deepcopy(agent.state_dict())
        batch, sim = collect(self, agent, *a, **kw)
        collected.append((snapshot, batch))
        return batch, sim

    def recording_update(agent, optimizer, batch, args, **kw):
        updated.append((copy.deepcopy(agent.state_dict()), batch))
        return update(agent, optimizer, batch, args, **kw)

    monkeypatch.setattr(ppo.Rollout, "collect", recording_collect)
    monkeypatch.setattr(ppo, "ppo_update", recording_update)
    res = run(tmp_path, total_env_steps=64, overlap=True, obs_norm=True)
    assert res["iterations"] == 4 and len(collected) == len(updated) == 4  # nothing collected past the budget
    saved = torch.load(res["checkpoint"], weights_only=False)
    for k, ((learner, batch), (acted, collected_batch)) in enumerate(zip(updated, collected)):
        assert batch is collected_batch  # update k trains on rollout k, its own storage (not overwritten since)
        agent = ppo.Agent(None, batch["obs"]["state"].shape[1], batch["actions"].shape[1], state_net="mlp",
                          obs_norm=True)  # fmt: skip
        agent.load_state_dict(acted)
        with torch.no_grad():
            _, logp, _, value = agent.get_action_and_value(batch["obs"], batch["actions"])
        torch.testing.assert_close(logp, batch["logprobs"], rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(value.view(-1), batch["values"], rtol=1e-5, atol=1e-5)
        behind = updated[max(k - 1, 0)][0]  # the learner's weights when update k-1 started
        assert all(torch.equal(acted[name], behind[name]) for name in acted), k
        if k >= 1:  # and not the weights that train on it
            assert not all(torch.equal(acted[name], learner[name]) for name in acted), k
    assert saved["counters"]["env_steps"] == 64


def test_a_save_then_resume_continues_without_losing_or_double_counting(tmp_path, stepped, monkeypatch):
    """A run that ends with a rollout collected ahead (the wall guard, an error) counts only the iterations
    trained; --resume collects anew from there. An error in the update stops the collection in flight first."""
    update, calls = ppo.ppo_update, []

    def fails_third(*a, **kw):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("the third update fails")
        return update(*a, **kw)

    monkeypatch.setattr(ppo, "ppo_update", fails_third)
    with pytest.raises(RuntimeError, match="third update"):
        run(tmp_path, total_env_steps=64, overlap=True)
    latest = tmp_path / "t" / "checkpoints" / "latest.pt"
    saved = torch.load(latest, weights_only=False)["counters"]
    assert (saved["iteration"], saved["env_steps"]) == (2, 32)
    assert 48 <= stepped[0] <= 64  # three rollouts, and at most a fourth cut short by the failure
    monkeypatch.setattr(ppo, "ppo_update", update)
    stepped[0] = 0
    again = run(tmp_path, total_env_steps=64, overlap=True, resume=latest)
    assert (again["iterations"], again["iterations_this_run"], again["env_steps"]) == (4, 2, 64)
    assert stepped[0] == 32  # the two iterations left, nothing more


def test_overlap_with_the_gpu_batched_env_is_one_line(refused):
    refused("agents.ppo", ["--overlap", "--backend", "gpu"], "--overlap steps the CPU envs")
