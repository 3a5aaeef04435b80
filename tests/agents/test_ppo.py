"""PPO trainer: one real iteration on 2 CPU workers from pixels, resume, evaluation, bad checkpoints."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.optim as optim

from agents.common import torch_threads
from agents.common.precision import native_bf16
from agents.ppo import Agent, Args, bootstrap_mask, main, ppo_update, succeeded_mask

REPO = Path(__file__).resolve().parents[2]
NATIVE_BF16 = native_bf16(torch.device("cpu"))
SHORT = 10  # the runs' episode length: what these tests check needs no full-length episode


def run(tmp_path: Path, **kw):
    base = dict(
        num_envs=2,
        num_steps=8,
        total_env_steps=16,
        eval_freq=0,
        save_freq=1,
        runs_dir=tmp_path,
        exp_name="t",
        progress=False,
        eval_freq_episodes=1,
        env_kwargs=dict(max_episode_steps=SHORT),  # evaluations and validations of a few steps, not 150-250
    )
    if kw.get("evaluate"):
        base["eval_episodes"] = 1  # --evaluate's episodes
    base.update(kw)
    return main(Args(**base))


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ppo")
    return tmp, run(tmp, obs="rgbd")


def test_one_rgbd_iteration_writes_events_and_checkpoint(trained):
    tmp, result = trained
    run_dir = Path(result["run_dir"])
    assert result["global_step"] == 16 and result["iterations"] == 1
    assert list(run_dir.glob("events.out.tfevents.*"))
    ckpt = torch.load(run_dir / "checkpoints" / "latest.pt", weights_only=False)
    assert ckpt["counters"]["env_steps"] == 16
    # the run's last word is written without a held-out evaluation too (--eval-episodes 0)
    assert json.loads((run_dir / "summary.json").read_text()) == {k: v for k, v in result.items() if k != "history"}
    assert ckpt["signature"]["image_shape"] == [84, 84, 4]
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ea = EventAccumulator(str(run_dir))
    ea.Reload()
    tags = ea.Tags()["scalars"]
    for t in ("charts/SPS", "losses/policy_loss", "losses/value_loss", "losses/approx_kl", "losses/entropy"):
        assert t in tags


def test_resume_continues_step_counter(trained):
    tmp, result = trained
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        again = run(tmp, obs="rgbd", total_env_steps=32, resume=Path(result["checkpoint"]))
        assert torch.get_num_threads() == 2  # the run's one learner thread beside its workers ends with it
    finally:
        torch.set_num_threads(threads)
    assert again["global_step"] == 32 and again["iterations"] == 2 and again["iterations_this_run"] == 1


def test_evaluate_writes_video_and_summary(trained):
    tmp, result = trained
    summary = run(tmp, obs="rgbd", evaluate=True, checkpoint=Path(result["checkpoint"]), exp_name=None)
    out = Path(result["run_dir"]) / "eval"
    data = json.loads((out / "summary.json").read_text())  # the held-out seeds, scored as the benchmark scores
    assert data["episodes"] == 1 and "success_rate" in data and data["successes"] == summary["successes"]
    videos = list((out / "videos").glob("*.mp4"))
    assert videos and videos[0].stat().st_size > 1000


def test_bad_and_mismatched_checkpoints(trained, tmp_path):
    tmp, result = trained
    with pytest.raises(FileNotFoundError, match="does not exist"):
        run(tmp_path, obs="rgbd", evaluate=True, checkpoint=tmp_path / "nope.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable"):
        run(tmp_path, obs="rgbd", evaluate=True, checkpoint=junk)
    with pytest.raises(ValueError, match="its networks differ from this run"):  # rgbd weights into a state-obs run
        run(tmp_path, obs="state", evaluate=True, checkpoint=Path(result["checkpoint"]))


def test_loss_decreases_on_fixed_batch():
    torch.manual_seed(0)
    agent = Agent((84, 84, 4), 20, 5)
    n = 16
    obs = {
        "rgb": torch.randint(0, 255, (n, 84, 84, 3), dtype=torch.uint8),
        "depth": torch.randint(0, 2000, (n, 84, 84, 1), dtype=torch.int16),
        "state": torch.randn(n, 20),
    }
    with torch.no_grad():
        actions, logp, _, values = agent.get_action_and_value(obs)
    batch = dict(
        obs=obs,
        actions=actions,
        logprobs=logp,
        values=values.view(-1),
        advantages=torch.randn(n),
        returns=torch.randn(n) * 2 + 1,
    )
    args = Args(update_epochs=1, num_minibatches=1, target_kl=None)
    opt = optim.Adam(agent.parameters(), lr=1e-3)
    losses = [ppo_update(agent, opt, batch, args)["value_loss"] for _ in range(10)]
    assert losses[-1] < 0.5 * losses[0]


def test_bootstrap_truncations_and_successes_not_failures():
    t, f = True, False
    info = {
        "_final_info": torch.tensor([t, t, t, f, t]),
        "final_info": {"fail": torch.tensor([t, f, f, f, t]), "success": torch.tensor([f, t, f, f, t])},
    }
    term = torch.tensor([t, t, f, f, t])  # collision, delivery, time limit, still running, delivered colliding
    assert bootstrap_mask(info, term).tolist() == [f, t, t, f, f]
    assert succeeded_mask(info, term).tolist() == [f, t, f, f, f]  # --absorbing-success: only the clean delivery


def test_absorbing_success_is_refused_for_a_reward_that_does_not_pay_one_a_step():
    with pytest.raises(ValueError, match="--absorbing-success values success at 1 a step.*'dense'"):
        main(Args(absorbing_success=True, reward_mode="dense"))


def test_critic_warmup_leaves_policy_untouched():
    torch.manual_seed(0)
    agent = Agent(None, 20, 5)
    obs = {"state": torch.randn(64, 20)}
    with torch.no_grad():
        actions, logp, _, values = agent.get_action_and_value(obs)
    batch = dict(
        obs=obs,
        actions=actions,
        logprobs=logp,
        values=values.view(-1),
        advantages=torch.randn(64),
        returns=torch.randn(64) * 2 + 1,
    )
    frozen = [p.clone() for p in list(agent.actor_mean.parameters()) + list(agent.encoder.parameters())]
    opt = optim.Adam(agent.parameters(), lr=1e-3)
    losses = [
        ppo_update(agent, opt, batch, Args(update_epochs=1, num_minibatches=1), critic_only=True)["value_loss"]
        for _ in range(10)
    ]
    assert losses[-1] < 0.5 * losses[0]
    now = list(agent.actor_mean.parameters()) + list(agent.encoder.parameters())
    assert all(torch.equal(a, b) for a, b in zip(frozen, now))


def test_a_residual_policy_starts_at_its_base_and_its_kl_pulls_back():
    torch.manual_seed(0)
    agent = Agent(None, 6, 5, residual=True, init_logstd=-2.0)
    obs = {"state": torch.randn(32, 6)}
    base = agent.base_action(obs)
    assert torch.equal(agent.get_action(obs, deterministic=True), base)  # the residual head starts at zero
    _, _, _, _, mean = agent.get_action_and_value(obs, with_mean=True)
    assert agent.kl_to_base(obs, mean).abs().max() < 1e-6
    with torch.no_grad():
        agent.actor_mean[-1].bias.fill_(0.3)  # a policy that drifted 0.3 from the base on every axis
    _, _, _, _, mean = agent.get_action_and_value(obs, with_mean=True)
    kl = agent.kl_to_base(obs, mean)
    assert kl.mean().item() == pytest.approx(5 * 0.3**2 / (2 * torch.exp(torch.tensor(-4.0)).item()), rel=1e-4)
    # the base is frozen: an update moves the residual and the std only
    before = [p.clone() for p in agent.base.parameters()]
    opt = optim.Adam([p for p in agent.parameters() if p.requires_grad], lr=1e-2)
    kl.mean().backward()
    opt.step()
    assert all(torch.equal(a, b) for a, b in zip(before, agent.base.parameters()))
    assert agent.actor_mean[-1].bias.abs().max() < 0.3


def test_fine_tuning_a_dagger_policy_with_kl_resume_and_evaluate(tmp_path, tiny_dagger):
    base = tiny_dagger(tmp_path, exp_name="base", env_kwargs=dict(max_episode_steps=SHORT))
    kw = dict(obs="state", action_frame="world", base_checkpoint=Path(base["checkpoint"]), kl_coef=1.0)
    res = run(tmp_path, init_logstd=-2.0, eval_episodes=1, **kw)
    saved = torch.load(res["checkpoint"], weights_only=False)
    assert saved["signature"]["residual"] and any(k.startswith("base.") for k in saved["model"])
    assert "losses/kl_to_base" in res["history"][-1]
    # the base travels in the checkpoint: resuming and evaluating need no --base-checkpoint
    again = run(tmp_path, obs="state", action_frame="world", kl_coef=1.0, resume=Path(res["checkpoint"]),
                total_env_steps=32)  # fmt: skip
    assert again["global_step"] > res["global_step"]
    ev = run(tmp_path, obs="state", action_frame="world", evaluate=True, checkpoint=Path(res["checkpoint"]),
             capture_video=False)  # fmt: skip
    assert ev["episodes"] == 1
    # sim2real-eval loads the fine-tuned policy, base and all, in its frame
    from maniskill_irb120.sim2real.policy import load_policy

    sim_env, make_policy = load_policy(res["checkpoint"], "TableClearing-IRB120-v1", "tool_delta")
    try:
        assert make_policy(sim_env).world_frame
    finally:
        sim_env.close()
    with pytest.raises(ValueError, match="'world' frame; pass --action-frame world"):
        run(tmp_path, obs="state", evaluate=True, checkpoint=Path(res["checkpoint"]), capture_video=False)
    with pytest.raises(ValueError, match="acts in the 'world' frame"):  # a base from another frame
        run(tmp_path, obs="state", base_checkpoint=Path(base["checkpoint"]))
    with pytest.raises(ValueError, match="give --base-checkpoint"):
        run(tmp_path, obs="state", kl_coef=1.0)


def test_running_norm_merges_batches_like_one_and_zeroes_constant_dims():
    from maniskill_irb120.policies.nets import RunningNorm

    g = torch.Generator().manual_seed(0)
    x = torch.randn(300, 3, generator=g) * torch.tensor([2.0, 0.005, 0.0]) + torch.tensor([1.0, 0.5, 7.0])
    norm = RunningNorm(3)
    for part in x.split([10, 90, 200]):
        norm.update(part)
    assert torch.allclose(norm.mean, x.mean(0), atol=1e-5)
    assert torch.allclose(norm.var, x.var(0, unbiased=False), rtol=1e-4, atol=1e-9)
    out = norm(dict(state=x))["state"]
    assert abs(float(out[:, 0].std()) - 1.0) < 0.01  # metres to unit scale
    assert abs(float(out[:, 1].std()) - 1.0) < 0.01  # millimetres to unit scale (a grasp's precision)
    assert float(out[:, 2].abs().max()) == 0.0  # never varied: zeroed, not amplified
    assert float(norm(dict(state=torch.full((1, 3), 1e6)))["state"].max()) == 10.0  # clipped


def test_state_mlp_with_obs_norm_trains_saves_and_acts_the_same_after_loading(tmp_path):
    """The from-scratch recipe's network: its normaliser learns from the rollouts and travels with the policy."""
    from maniskill_irb120.policies import policy_module, read_policy_section

    res = run(tmp_path, obs="state", state_net="mlp", obs_norm=True, env_id="GraspLift-IRB120-v1", select_episodes=1)
    saved = torch.load(res["checkpoint"], weights_only=False)
    # checkpoint selection ran at the end: one validation episode, its winner is best.pt
    assert res["selected"]["iteration"] == 1 and res["selected"]["validation_episodes"] == 1
    assert res["checkpoint"].endswith("best.pt") and res["last_checkpoint"].endswith("latest.pt")
    assert torch.equal(
        torch.load(res["last_checkpoint"], weights_only=False)["model"]["norm.count"], saved["model"]["norm.count"]
    )
    assert saved["signature"]["state_net"] == "mlp" and saved["signature"]["obs_norm"]
    assert float(saved["model"]["norm.count"]) == 16  # two iterations of 8 steps (the first acted unnormalised)
    module = policy_module(read_policy_section(Path(res["checkpoint"])))
    agent = Agent(None, module.state_dim, module.action_dim, state_net="mlp", obs_norm=True)
    agent.load_state_dict(saved["model"])
    obs = dict(state=torch.randn(4, module.state_dim))
    assert torch.equal(module.get_action(obs, deterministic=True), agent.get_action(obs, deterministic=True))
    with pytest.raises(ValueError, match="no camera"):
        Agent((84, 84, 4), 20, 5, state_net="mlp")
    with pytest.raises(ValueError, match="unknown state_net"):
        Agent(None, 20, 5, state_net="wide")


def test_a_state_dependent_log_std_starts_at_its_init_and_learns_a_different_noise_per_state():
    """Two kinds of state: in one the rewarded action is exactly the mean (a still hold), in the other it is spread
    around it. Maximising their log-likelihood shrinks the noise in the first and keeps it in the second; the
    learned parameter of the default policy can only pick one noise for both."""
    torch.manual_seed(0)
    states = torch.randn(64, 6)
    states[:, 0] = torch.where(torch.arange(64) < 32, 3.0, -3.0)  # the first half "holds", the second "explores"
    hold = torch.arange(64) < 32
    obs = {"state": states}

    def fit(agent) -> tuple[float, float]:
        opt = optim.Adam(agent.parameters(), lr=1e-2)  # 100 steps at 1e-2: what 300 at 3e-3 learned, in a third
        for _ in range(100):
            x = agent.features(obs)
            mean = agent.mean(obs, x).detach()
            target = torch.where(hold[:, None], mean, mean + torch.randn_like(mean))
            _, logprob, _, _ = agent.get_action_and_value(obs, target)
            opt.zero_grad()
            (-logprob.mean()).backward()
            opt.step()
        with torch.no_grad():
            x = agent.features(obs)
            logstd = agent.log_std(x, agent.mean(obs, x)).mean(1)
        return logstd[hold].mean().item(), logstd[~hold].mean().item()

    agent = Agent(None, 6, 5, state_net="mlp", logstd="state", init_logstd=-0.5)
    with torch.no_grad():
        x = agent.features(obs)
        assert torch.allclose(agent.log_std(x, agent.mean(obs, x)), torch.full((64, 5), -0.5))
    with torch_threads(1):  # a 64-row MLP: a second thread only waits on a loaded box (7 s with one, 40 with two)
        held, explored = fit(agent)
        shared, shared_too = fit(Agent(None, 6, 5, state_net="mlp", init_logstd=-0.5))
    assert held < -2.0 and abs(explored) < 0.3  # still where holding, about N(0, 1)'s spread elsewhere
    assert shared == shared_too and shared > -1.0  # one log std for both: between the two
    with pytest.raises(ValueError, match="no residual form"):
        Agent(None, 6, 5, residual=True, logstd="state")
    with pytest.raises(ValueError, match="unknown logstd"):
        Agent(None, 6, 5, logstd="wide")


def test_a_state_dependent_log_std_trains_saves_evaluates_and_loads_as_a_policy(tmp_path):
    from maniskill_irb120.policies import acting, read_policy_section

    kw = dict(obs="state", state_net="mlp", obs_norm=True, env_id="GraspLift-IRB120-v1")
    res = run(tmp_path, logstd="state", **kw)
    saved = torch.load(res["checkpoint"], weights_only=False)
    assert saved["signature"]["logstd"] == "state" and "actor_logstd_head.4.bias" in saved["model"]
    section = read_policy_section(Path(res["checkpoint"]))
    agent = Agent(**section["config"])  # the section says what to build: logstd="state" among the rest
    agent.load_state_dict(saved["model"])
    assert agent.logstd == "state"
    obs = dict(state=torch.randn(4, section["config"]["state_dim"]))
    assert torch.equal(acting(section)(obs), agent.get_action(obs, deterministic=True))
    ev = run(tmp_path, evaluate=True, checkpoint=Path(res["checkpoint"]), logstd="state", capture_video=False, **kw)
    assert ev["episodes"] == 1
    one_log_std = r"logstd 'state' in the checkpoint, 'param' in this run \(pass --logstd state\)"
    with pytest.raises(ValueError, match=one_log_std):  # evaluated as a policy with one log std
        run(tmp_path, evaluate=True, checkpoint=Path(res["checkpoint"]), capture_video=False, **kw)


def test_checkpoint_selection_keeps_the_best_validation_and_the_held_out_evaluation_scores_it(tmp_path, monkeypatch):
    """A run that peaks and then unlearns keeps its peak: best.pt changes only on a better validation score (success,
    then return), the validation seeds are not the held-out ones, and the held-out evaluation loads best.pt."""
    import agents.ppo as ppo
    from agents.common import EVAL_SEED, VALIDATION_SEED

    scores = iter([(0.2, 5.0), (0.6, 9.0), (0.6, 8.0), (0.1, 2.0), (0.6, 8.5)])  # validations at iterations 1..5
    validations, held_out = [], []

    def scripted(agent, args, device, video_dir=None, first_seed=EVAL_SEED):
        if first_seed == EVAL_SEED:
            held_out.append(agent.actor_logstd.detach().clone())
            return dict(success_rate=0.0)
        validations.append((first_seed, args.eval_episodes))
        s, r = next(scores)
        return {"success_rate": s, "return": r}

    monkeypatch.setattr(ppo, "final_evaluation", scripted)
    res = run(
        tmp_path,
        obs="state",
        state_net="mlp",
        select_episodes=3,
        select_freq=1,
        total_env_steps=80,
        eval_episodes=1,
        learning_rate=0.05,
    )
    assert validations == [(VALIDATION_SEED, 3)] * 5
    assert res["selected"]["iteration"] == 2 and res["selected"]["validation_success_rate"] == 0.6
    ckpts = tmp_path / "t" / "checkpoints"
    best = torch.load(ckpts / "best.pt", weights_only=False)
    second = torch.load(ckpts / "ckpt_2.pt", weights_only=False)["model"]["actor_logstd"]
    last = torch.load(ckpts / "latest.pt", weights_only=False)["model"]["actor_logstd"]
    assert best["counters"]["best"]["iteration"] == 2 and torch.equal(best["model"]["actor_logstd"], second)
    assert not torch.equal(second, last)  # training moved on after the peak...
    assert len(held_out) == 1 and torch.equal(held_out[0], second)  # ...and the held-out evaluation scored the peak
    with pytest.raises(ValueError, match="--select-freq"):
        run(tmp_path, obs="state", select_episodes=2, select_freq=0)


def test_a_run_stopped_by_its_budget_validates_its_last_weights_once(tmp_path, monkeypatch):
    import agents.ppo as ppo
    from agents.common import VALIDATION_SEED

    validated = []

    def scripted(agent, args, device, video_dir=None, first_seed=VALIDATION_SEED):
        validated.append(first_seed)
        return {"success_rate": 0.0, "return": 0.0}

    monkeypatch.setattr(ppo, "final_evaluation", scripted)
    kw = dict(obs="state", state_net="mlp", select_episodes=1, total_env_steps=10**6, max_minutes=2 / 60)
    kw["eval_episodes"] = 0
    every = run(tmp_path / "every", select_freq=1, **kw)  # each iteration validated: the stop adds none
    assert every["iterations"] >= 1 and validated.count(VALIDATION_SEED) == every["iterations"]
    validated.clear()
    rare = run(tmp_path / "rare", select_freq=10**6, **kw)  # none validated in the loop: the stop validates
    assert (
        rare["iterations"] >= 1
        and validated == [VALIDATION_SEED]
        and rare["selected"]["iteration"] == rare["iterations"]
    )


def test_no_iteration_starts_that_would_end_after_the_budget(tmp_path, monkeypatch):
    """A stage of a staged recipe keeps to its minutes: an iteration and the validation after it start only where
    the longest of each so far still end within the budget. The clock jumps 100 s at each validation, so the stop
    is the budget's arithmetic and not this machine's speed (stopping once past the budget ran a third)."""
    import agents.ppo as ppo
    from agents.common import VALIDATION_SEED

    jumped = [0.0]

    class JumpingClock(ppo.Clock):
        def __call__(self) -> float:
            return super().__call__() + jumped[0]

    def scripted(agent, args, device, video_dir=None, first_seed=VALIDATION_SEED):
        jumped[0] += 100.0
        return {"success_rate": 0.0, "return": 0.0}

    monkeypatch.setattr(ppo, "Clock", JumpingClock)
    monkeypatch.setattr(ppo, "final_evaluation", scripted)
    kw = dict(obs="state", state_net="mlp", select_episodes=1, select_freq=1, total_env_steps=10**6, eval_episodes=0)
    res = run(tmp_path, max_minutes=250.0 / 60, **kw)
    assert res["iterations"] == 2 and 200.0 < res["wall_clock_s"] <= 250.0


def test_minibatches_of_one_row_are_refused_before_training(tmp_path):
    with pytest.raises(ValueError, match="fewer than 2 rows"):
        run(tmp_path, obs="state", num_envs=1, num_steps=4, num_minibatches=4)


def test_the_budget_spans_a_resume(tmp_path):
    """--budget-min is the run's, as in DAgger and SAC: a resumed run trains only what its checkpoint left of it."""
    kw = dict(obs="state", state_net="mlp", total_env_steps=10**6, eval_episodes=0, num_envs=1, num_steps=8)
    first = run(tmp_path, budget_min=0.02, **kw)
    assert first["iterations"] >= 1
    again = run(tmp_path, budget_min=0.02, resume=Path(first["checkpoint"]), **kw)
    assert again["iterations_this_run"] == 0 and again["wall_clock_s"] >= first["wall_clock_s"]
    # a budget a few seconds past what the run spent and its longest iteration (the checkpoint's estimate)
    step_s = torch.load(again["checkpoint"], weights_only=False)["counters"]["step_s"]
    more = again["wall_clock_s"] + step_s + 3.0
    longer = run(tmp_path, budget_min=more / 60, resume=Path(again["checkpoint"]), **kw)
    assert longer["iterations_this_run"] >= 1 and again["wall_clock_s"] < longer["wall_clock_s"]


def test_an_exception_mid_training_keeps_the_iterations_done_and_resume_carries_on(tmp_path, monkeypatch):
    """No checkpoint is lost: an exception (or Ctrl-C) in iteration 2, after its rollout, leaves latest.pt with the
    one iteration done and the clock, though --save-freq would not have saved yet; --resume continues from it."""
    import agents.ppo as ppo

    update, calls = ppo.ppo_update, []

    def fails_second(*a, **kw):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("the second update fails")
        return update(*a, **kw)

    monkeypatch.setattr(ppo, "ppo_update", fails_second)
    kw = dict(obs="state", state_net="mlp", num_envs=1, num_steps=8, num_minibatches=2, total_env_steps=32)
    with pytest.raises(RuntimeError, match="second update"):
        run(tmp_path, save_freq=100, **kw)
    ckpts = tmp_path / "t" / "checkpoints"
    assert sorted(p.name for p in ckpts.iterdir()) == ["latest.pt"]
    saved = torch.load(ckpts / "latest.pt", weights_only=False)["counters"]
    assert saved["iteration"] == 1 and saved["env_steps"] == 8 and saved["wall_s"] > 0  # not iteration 2's rollout
    assert not (tmp_path / "t" / "summary.json").exists()
    monkeypatch.undo()
    again = run(tmp_path, resume=ckpts / "latest.pt", save_freq=100, **kw)
    assert (again["iterations"], again["iterations_this_run"], again["global_step"]) == (4, 3, 32)
    assert again["wall_clock_s"] > saved["wall_s"]  # the clock carries on from the checkpoint's
    other_net = "--resume .*latest.pt: its networks differ from this run.s: .*pass --state-net mlp"
    with pytest.raises(ValueError, match=other_net):
        run(tmp_path, **{**kw, "state_net": "shared"}, resume=ckpts / "latest.pt")


def test_the_trainer_takes_a_held_out_curve_at_shares_of_its_budget(tmp_path):
    """--curve-points in agents.ppo (the loop's, shared by every trainer): the policy as it trains on held-out seeds
    at a quarter, a half and three quarters of 64 env steps (16 a PPO iteration), kept in summary.json."""
    result = run(tmp_path, obs="state", total_env_steps=64, curve_points=4, curve_episodes=2, eval_episodes=2)
    rows = result["held_out_curve"]
    assert [r[0] for r in rows] == [16, 32, 48] and all(len(r[3]) == 2 and r[2] == sum(r[3]) / 2 for r in rows)
    assert json.loads((Path(result["run_dir"]) / "summary.json").read_text())["held_out_curve"] == rows


def test_periodic_checkpoints_keep_the_newest_and_never_latest_or_best(tmp_path):
    """A long camera run writes a 17 MB ckpt_N.pt every --save-freq iterations: only the newest
    --keep-checkpoints stay, ordered by N (not by name: ckpt_10 is newer than ckpt_9), and 0 keeps every one."""
    from agents.ppo import prune_checkpoints

    result = run(tmp_path, obs="state", total_env_steps=64, keep_checkpoints=2)  # 4 iterations, one each
    ckpt_dir = Path(result["run_dir"]) / "checkpoints"
    assert sorted(p.name for p in ckpt_dir.glob("*.pt")) == ["ckpt_3.pt", "ckpt_4.pt", "latest.pt"]
    assert torch.load(ckpt_dir / "ckpt_4.pt", weights_only=False)["counters"]["iteration"] == 4

    names = ["ckpt_9.pt", "ckpt_10.pt", "ckpt_11.pt", "best.pt", "latest.pt", "ckpt_notes.pt"]
    for name in names:
        (tmp_path / name).write_bytes(b"x")
    assert prune_checkpoints(tmp_path, 0) == []
    assert [p.name for p in prune_checkpoints(tmp_path, 2)] == ["ckpt_9.pt"]
    assert sorted(p.name for p in tmp_path.glob("*.pt")) == sorted(set(names) - {"ckpt_9.pt"})
    with pytest.raises(ValueError, match="--keep-checkpoints must be >= 0"):
        run(tmp_path, obs="state", keep_checkpoints=-1)


def test_the_env_step_budget_spans_a_resume_and_the_summary_records_it(tmp_path):
    """--total-env-steps is the run's: a resumed run counts the env steps its checkpoint had done, so it trains only
    what is left of the budget, and one given again (a larger one) trains on to it."""
    kw = dict(obs="state", state_net="mlp", eval_episodes=0, num_envs=1, num_steps=8, num_minibatches=2)
    first = run(tmp_path, total_env_steps=16, **kw)
    assert first["iterations"] == 2 and first["env_steps"] == 16
    summary = json.loads((tmp_path / "t" / "summary.json").read_text())
    assert summary["total_env_steps"] == 16 and summary["stopped_early"] is False and summary["wall_clock_s"] > 0
    again = run(tmp_path, total_env_steps=16, resume=Path(first["checkpoint"]), **kw)
    assert again["iterations_this_run"] == 0 and again["env_steps"] == 16
    longer = run(tmp_path, total_env_steps=40, resume=Path(again["checkpoint"]), **kw)
    # 16 done before: 3 iterations of 8 start below 40, the last one ending on it
    assert longer["iterations_this_run"] == 3 and longer["env_steps"] == 40 and longer["total_env_steps"] == 40


def test_a_run_the_guard_stops_before_its_env_steps_says_so(tmp_path, capsys):
    kw = dict(obs="state", state_net="mlp", eval_episodes=0, num_envs=1, num_steps=8, num_minibatches=2)
    res = run(tmp_path, total_env_steps=10**6, max_minutes=0.01, **kw)
    assert res["stopped_early"] is True and res["total_env_steps"] == 10**6 and 0 < res["env_steps"] < 10**6
    assert f"stopped early at {res['env_steps']} env steps (of 1000000)" in capsys.readouterr().out.splitlines()


def camera_batch(n: int = 32, seed: int = 0) -> tuple[Agent, dict]:
    """A camera agent (the ppo-rgbd recipe's network at 84x84) and a batch of its own samples on random images."""
    torch.manual_seed(seed)
    agent = Agent((84, 84, 4), 29, 7, obs_norm=True)
    obs = {
        "rgb": torch.randint(0, 256, (n, 84, 84, 3), dtype=torch.uint8),
        "depth": torch.randint(0, 2000, (n, 84, 84, 1), dtype=torch.int16),
        "state": torch.randn(n, 29),
    }
    with torch.no_grad():
        actions, logp, _, values = agent.get_action_and_value(obs)
    returns = values.view(-1) + torch.randn(n)
    batch = dict(obs=obs, actions=actions, logprobs=logp, values=values.view(-1), returns=returns,
                 advantages=returns - values.view(-1))  # fmt: skip
    return agent, batch


@pytest.mark.skipif(not NATIVE_BF16, reason="this CPU has no native bf16")
def test_a_bf16_update_trains_the_encoder_finitely_with_float32_heads_and_losses():
    agent, batch = camera_batch()
    before = {k: v.clone() for k, v in agent.state_dict().items()}
    # the heads read float32 features: log-probabilities and values are float32, and near the fp32 ones
    _, logp, _, value = agent.get_action_and_value(batch["obs"], batch["actions"], precision="bf16")
    assert logp.dtype == value.dtype == torch.float32
    assert (logp - batch["logprobs"]).abs().max() < 1e-2  # the ratio starts near 1, as in fp32
    opt = optim.Adam(agent.parameters(), lr=1e-3)
    stats = ppo_update(agent, opt, batch, Args(update_epochs=2, num_minibatches=2, target_kl=None, precision="bf16"))
    assert all(np.isfinite(v) for v in stats.values()), stats
    after = agent.state_dict()
    assert all(after[k].dtype == v.dtype for k, v in before.items())  # weights stay float32
    assert all(torch.isfinite(after[k]).all() for k in before if after[k].is_floating_point())
    conv = "encoder.cnn.0.weight"
    assert not torch.equal(before[conv], after[conv])  # the encoder learned under autocast
    assert not torch.equal(before["critic.2.weight"], after["critic.2.weight"])


@pytest.mark.skipif(not NATIVE_BF16, reason="this CPU has no native bf16")
def test_bf16_and_fp32_features_agree_to_bf16_rounding():
    agent, batch = camera_batch(8)
    with torch.no_grad():
        fp32, bf16 = agent.features(batch["obs"]), agent.features(batch["obs"], "bf16")
    assert bf16.dtype == torch.float32 and not torch.equal(fp32, bf16)  # autocast ran: bf16 rounding is visible
    assert torch.allclose(fp32, bf16, rtol=0.05, atol=0.05)


def test_an_unresolved_precision_is_refused():
    agent, batch = camera_batch(4)
    with pytest.raises(ValueError, match="precision 'auto' is not resolved"):
        agent.features(batch["obs"], "auto")


def test_bf16_without_native_support_is_refused_before_anything_runs(monkeypatch):
    import agents.common.precision as precision

    monkeypatch.setattr(precision, "native_bf16", lambda device: False)
    with pytest.raises(ValueError, match="--precision bf16: cpu has no native bfloat16"):
        main(Args(precision="bf16", device="cpu"))
    assert precision.resolve_precision("auto", torch.device("cpu")) == "fp32"  # auto falls back


def test_an_unknown_precision_is_one_line_and_exit_code_2():
    import subprocess
    import sys

    run = subprocess.run(
        [sys.executable, "-m", "agents.ppo", "--precision", "fp16"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert run.returncode == 2 and "invalid choice 'fp16' for argument '--precision'" in run.stderr, run.stderr
    assert "Traceback" not in run.stderr and len(run.stderr.strip().splitlines()) == 1


def test_a_sigterm_to_the_group_ends_a_training_run_as_a_ctrl_c_does(tmp_path, terminate_group):
    """A scheduler's stop or a session's end sends SIGTERM, often to the whole process group: the trainer takes it
    as a Ctrl-C (saves latest.pt, closes its worker envs, one line naming --resume, exit 130), and the workers
    ignore it, so none of them prints a traceback; the run then continues from latest.pt."""
    import sys

    argv = [sys.executable, "-m", "agents.ppo", "--obs", "state", "--env-id", "GraspLift-IRB120-v1"]
    argv += ["--num-envs", "2", "--num-steps", "8", "--num-minibatches", "1", "--update-epochs", "1"]
    argv += ["--total-env-steps", "1000000", "--save-freq", "1", "--select-episodes", "0", "--eval-episodes", "0"]
    argv += ["--runs-dir", str(tmp_path), "--exp-name", "t", "--no-progress", "--no-capture-video"]
    ckpts = tmp_path / "t" / "checkpoints"
    code, own = terminate_group(argv, lambda: any(ckpts.glob("ckpt_*.pt")))  # training: its first iterations saved
    assert code == 130 and own == ["agents.ppo: interrupted; --resume RUN/checkpoints/latest.pt continues the run"], own
    saved = torch.load(ckpts / "latest.pt", weights_only=False)
    assert saved["counters"]["env_steps"] >= 16
