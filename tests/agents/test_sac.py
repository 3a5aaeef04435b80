"""agents.sac (RLPD-style SAC with demos): replay rows use the real final observation, minibatches mix demos
at the asked ratio, cloning from the demos moves the actor onto the expert, and tiny state and rgbd runs
write results, checkpoints and logs that resume and evaluate; bad input is named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from agents.common import Dataset
from agents.sac import (
    SAC,
    Args,
    collect_demos,
    demo_rows,
    main,
    make_envs,
    online_rows,
    pretrain,
    sample,
    split,
    transitions,
    update,
)


def tiny(tmp_path: Path, **kw) -> dict:
    """A toy run sized in env steps (the expert's demo episode and the rest online), with a budget far above it: the
    same run on a quiet machine and on a loaded CI box. Episodes end at 25 steps, the held-out evaluations' too (the
    task's 250 steps each, in three evaluations of the state test)."""
    base = dict(
        env_kwargs=dict(max_episode_steps=25),
        budget_min=5.0,
        total_env_steps=310,
        num_envs=1,
        demo_episodes=1,
        bc_pretrain_updates=5,
        critic_warmup_updates=5,
        learning_starts=10,
        batch_size=16,
        log_freq=20,
        save_freq=40,
        eval_episodes=1,
        runs_dir=tmp_path,
        exp_name="t",
        progress=False,
        capture_video=False,
    )
    base.update(kw)
    return main(Args(**base))


def test_replay_rows_take_the_final_observation_where_an_episode_ended():
    obs = {"state": torch.zeros(2, 3)}
    after_reset = torch.full((2, 3), 5.0)
    info = {"final_observation": torch.full((2, 3), 9.0), "_final_observation": torch.tensor([False, True])}
    row, _ = transitions(
        obs, torch.zeros(2, 5), torch.tensor([0.1, 1.0]), torch.tensor([False, True]), after_reset, info
    )
    assert row["next_state"][0].tolist() == [5.0] * 3 and row["next_state"][1].tolist() == [9.0] * 3
    assert row["term"].tolist() == [0.0, 1.0] and row["rew"].tolist() == pytest.approx([0.1, 1.0])


def test_minibatches_mix_demos_at_the_asked_ratio():
    demos, online = Dataset(100), Dataset(100)
    rows = lambda v: dict(
        state=torch.full((50, 2), v), rew=torch.zeros(50), term=torch.zeros(50), next_state=torch.zeros(50, 2)
    )  # noqa: E731
    demos.add(rows(1.0), torch.zeros(50, 5))
    online.add(rows(2.0), torch.zeros(50, 5))
    batch, _, n_demo = sample(online, demos, Args(batch_size=40, demo_ratio=0.25), "cpu")
    assert n_demo == 10 and (batch["state"][:10] == 1).all() and (batch["state"][10:] == 2).all()
    obs, *_ = split(batch)
    assert set(obs) == {"state"}
    only_demos, _, n = sample(Dataset(10), demos, Args(batch_size=8), "cpu")  # no online data yet
    assert n == 8 and (only_demos["state"] == 1).all()


def test_cloning_moves_the_actor_onto_the_expert():
    args = Args(num_envs=1, batch_size=64, bc_pretrain_updates=300, critic_warmup_updates=0)
    envs = make_envs(args, 1)
    try:
        o, info = envs.reset(seed=5)
        state = dict(obs={"state": o}, label=info["expert_action"].float())
        demos = Dataset(10_000)
        collect_demos(envs, state, demos, 2, noise=0.2)
    finally:
        envs.close()
    rows = demos.obs
    # the expert delivers both: each episode's last row is an absorbing success, never a plain terminal
    assert rows["succ"][: demos.size].sum() == 2 and (rows["succ"][: demos.size] <= rows["term"][: demos.size]).all()
    # DART: the executed arm actions carry the noise, the clean labels (the cloning's targets) do not
    gap = demos.act[: demos.size] - rows["label"][: demos.size]
    assert 0.1 < gap[:, :4].std() < 0.3 and (gap[:, 4] == 0).all()
    torch.manual_seed(0)
    model = SAC(None, demos.obs["state"].shape[1], 5, 0.1)
    model.critic.norm.fit(demos.obs["state"][: demos.size])
    obs = {"state": demos.obs["state"][: demos.size]}
    target = demos.obs["label"][: demos.size]

    def error() -> float:
        return float(((model.act(obs, deterministic=True) - target) ** 2).mean())

    before = error()
    opts = dict(q=torch.optim.Adam(model.critic.parameters()))
    pretrain(model, opts, Dataset(1), demos, args, "cpu")
    assert error() < 0.3 * before, (before, error())


def test_success_targets_its_absorbing_return_and_failure_has_no_future():
    torch.manual_seed(0)
    model = SAC(None, 3, 5, 0.1)
    opts = dict(q=torch.optim.Adam(model.critic.parameters(), lr=0.0))  # lr 0: read the loss, move nothing
    obs, act = {"state": torch.zeros(1, 3)}, torch.zeros(1, 5)
    with torch.no_grad():
        q1, q2 = model.critic(model.critic.features(obs), act)

    def q_loss(rew: float, term: float, succ: float) -> float:
        row = dict(state=obs["state"], next_state=obs["state"], rew=torch.tensor([rew]), term=torch.tensor([term]))
        row["succ"] = torch.tensor([succ])
        return update(model, opts, row, act, 0, Args(gamma=0.9), actor=False)["q_loss"]

    # a delivery (reward 1.0) is worth 1 / (1 - 0.9) = 10, the value of staying at the maximum reward
    assert q_loss(1.0, 1.0, 1.0) == pytest.approx(float((q1 - 10) ** 2 + (q2 - 10) ** 2), rel=1e-4)
    # a collision (reward 0, terminal) is worth nothing after it
    assert q_loss(0.0, 1.0, 0.0) == pytest.approx(float(q1**2 + q2**2), rel=1e-4)


def test_the_clone_acts_and_bootstraps_where_the_critic_values_it_higher():
    torch.manual_seed(0)
    model = SAC(None, 3, 5, 0.1)
    model.freeze_reference()
    obs = {"state": torch.randn(64, 3)}
    clone = model.reference(obs)
    with torch.no_grad():
        model.actor.mean.bias.add_(0.5)  # the actor moves on; the frozen clone does not
        model.critic.encoder.mlp[0].bias.add_(0.5)
    assert torch.equal(model.reference(obs), clone)
    feats = model.critic.features(obs)
    actor = model.actor(feats)[2]
    chosen = model.act(obs, deterministic=True)
    with torch.no_grad():
        q_actor, q_clone = torch.min(*model.critic(feats, actor)), torch.min(*model.critic(feats, clone))
    pick_clone = q_clone > q_actor
    assert torch.equal(chosen[pick_clone], clone[pick_clone]) and torch.equal(chosen[~pick_clone], actor[~pick_clone])
    # bootstrapping takes the better of the two as well: a critic that prefers a[:, 0] picks per sample
    better, v = model.better(lambda f, a: (a[:, 0], a[:, 0] + 1), feats, actor, clone)
    assert torch.equal(v, torch.max(actor[:, 0], clone[:, 0]))
    assert torch.equal(better[:, 0], torch.max(actor[:, 0], clone[:, 0]))


def test_state_run_resume_and_evaluate(tmp_path, capsys):
    res = tiny(tmp_path)
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert {"success_rate", "successes", "env_steps", "wall_clock_s"} <= set(last) and last["env_steps"] > 0
    assert res["updates"] > 0 and (Path(res["run_dir"]) / "summary.json").is_file()
    assert list(Path(res["run_dir"]).glob("events.out.tfevents*"))
    saved = torch.load(res["checkpoint"], weights_only=False)
    rows = saved["data_rows"]  # the data beside the checkpoint, in data/online and data/demos
    assert rows["demos"]["added"] > 0 and rows["online"]["added"] > 0 and "online" not in saved
    assert saved["signature"]["reference"] and any(k.startswith("reference.") for k in saved["model"])
    # state's default replay; the demo buffer holds the demo episodes (1 + 1 env still running, the task's registered
    # 250 steps each: demo_rows reads the registry, not --env-kwargs)
    assert rows["online"]["capacity"] == 300_000 and rows["demos"]["capacity"] == 500
    assert saved["args"]["buffer_size"] == 300_000
    # the budget counts the first run's wall clock too: one it has already used up stops the resumed run at once
    spent = tiny(tmp_path, resume=Path(res["checkpoint"]), budget_min=0.001, total_env_steps=None)
    assert spent["env_steps"] == res["env_steps"] and spent["updates"] == res["updates"]
    again = tiny(tmp_path, resume=Path(res["checkpoint"]), total_env_steps=res["env_steps"] + 40)
    assert again["env_steps"] > res["env_steps"] and again["updates"] > res["updates"]
    assert again["wall_clock_s"] > res["wall_clock_s"]
    ev = tiny(tmp_path, evaluate=True, checkpoint=Path(res["checkpoint"]), capture_video=True)
    assert ev["episodes"] == 1 and list((tmp_path / "t" / "eval" / "videos").glob("*.mp4"))
    noisy = tiny(tmp_path, evaluate=True, checkpoint=Path(res["checkpoint"]), eval_deterministic=False)
    assert noisy["episodes"] == 1
    sim2real_acts_as_trained(Path(res["checkpoint"]), tmp_path)


def sim2real_acts_as_trained(ckpt: Path, tmp_path: Path) -> None:
    """sim2real-eval's --actions on this checkpoint: the mean, or samples seeded by the episode alone."""
    from maniskill_irb120.sim2real.policy import load_policy

    env_id = "TableClearing-IRB120-v1"
    sim_env, make_policy = load_policy(str(ckpt), env_id, "tool_delta", "sample")
    obs, _ = sim_env.reset(seed=0)
    policy, other = make_policy(sim_env), make_policy(sim_env)
    before = torch.random.get_rng_state()
    policy.reset(5), other.reset(5)
    first = policy.act(obs)
    assert torch.equal(first, other.act(obs))  # sim and real draw alike on one episode seed
    other.reset(6)
    assert not torch.equal(first, other.act(obs))
    assert torch.equal(before, torch.random.get_rng_state())  # torch's global draws are left alone
    sim_env.close()
    for actions, sampled in (("mean", False), ("as-trained", False)):
        sim_env, make_policy = load_policy(str(ckpt), env_id, "tool_delta", actions)
        assert make_policy(sim_env).sampled is sampled
        sim_env.close()
    saved = torch.load(ckpt, weights_only=False)
    saved["args"]["eval_deterministic"] = False  # as the sac-state recipe trains it
    saved["policy"]["eval_deterministic"] = False  # what sim2real-eval reads
    torch.save(saved, tmp_path / "noisy.pt")
    sim_env, make_policy = load_policy(str(tmp_path / "noisy.pt"), env_id, "tool_delta")
    assert make_policy(sim_env).sampled
    sim_env.close()
    with pytest.raises(ValueError, match="--actions 'greedy'"):
        load_policy(str(ckpt), env_id, "tool_delta", "greedy")
    with pytest.raises(ValueError, match="no distribution to sample"):
        load_policy("expert", env_id, "tool_delta", "sample")


def test_rgbd_run_learns_from_camera_and_proprioception(tmp_path):
    # a small replay: allocating RGB-D rows is slow after the RLlib tests (Ray's object store holds shared
    # memory; the old 300k-row default took 29 s, profiled: torch.empty). Sized in env steps (tiny), not seconds: a
    # budget of 6 s, then 18, once went to rendering the demo alone while CI loaded both cores (0 updates)
    res = tiny(
        tmp_path,
        obs="rgbd",
        total_env_steps=140,
        batch_size=8,
        bc_pretrain_updates=2,
        critic_warmup_updates=2,
        buffer_size=2000,
    )
    saved = torch.load(res["checkpoint"], weights_only=False)
    assert saved["signature"]["image_shape"] == [84, 84, 4] and saved["signature"]["state_dim"] < 40
    assert res["updates"] > 0


def test_bad_input_is_named(tmp_path):
    with pytest.raises(ValueError, match="demo-ratio"):
        main(Args(demo_ratio=1.5))
    with pytest.raises(ValueError, match="--checkpoint"):
        main(Args(evaluate=True))
    with pytest.raises(ValueError, match="--buffer-size 0"):
        main(Args(buffer_size=0))
    with pytest.raises(ValueError, match="--total-env-steps must be a positive number"):
        main(Args(total_env_steps=0))
    wrong = tmp_path / "dagger.pt"
    torch.save(dict(format="maniskill_irb120.dagger/1"), wrong)
    with pytest.raises(ValueError, match="not written by agents.sac"):
        main(Args(evaluate=True, checkpoint=wrong))


def test_replay_sizes_fit_the_observation():
    assert online_rows(Args(obs="state")) == 300_000 and online_rows(Args(obs="rgbd")) == 50_000  # ~3.5 GB
    assert online_rows(Args(obs="rgbd", buffer_size=100_000)) == 100_000
    assert demo_rows(Args(demo_episodes=30, num_envs=2)) == 32 * 250 and demo_rows(Args(demo_episodes=0)) >= 1


def test_without_demos_the_normaliser_is_fitted_on_the_steps_before_learning(tmp_path):
    """SAC from the reward alone (the sac-scratch-state recipe): no demos to fit StateNorm on, so the random
    steps before ``learning_starts`` are; target and online critics share it."""
    res = tiny(
        tmp_path, demo_episodes=0, bc_pretrain_updates=0, critic_warmup_updates=0, reference=False, actor_delay=0
    )
    saved = torch.load(res["checkpoint"], weights_only=False)
    assert saved["counters"]["norm_fitted"] and res["updates"] > 0
    std, mean = saved["model"]["critic.norm.std"], saved["model"]["critic.norm.mean"]
    assert torch.isfinite(std).sum() > 10 and not torch.all(mean == 0)  # fitted, not the identity
    assert torch.equal(saved["model"]["target.norm.std"], std)


def test_total_env_steps_is_the_budget_with_no_clock_unless_asked_for(tmp_path):
    """--total-env-steps ends the run, demos counted, with no wall guard of its
    own; the summary names the budget and that no guard stopped it."""
    res = tiny(tmp_path, budget_min=None, total_env_steps=200)
    assert 200 <= res["env_steps"] < 200 + 250 and res["total_env_steps"] == 200
    assert res["max_minutes"] is None and res["stopped_early"] is False
    summary = json.loads((tmp_path / "t" / "summary.json").read_text())
    assert summary["total_env_steps"] == 200 and summary["env_steps"] == res["env_steps"]
