"""PPO from pixels' two opt-in aids (issue 92): DrQ's random shift of the update's images (``--augment shift``) and an
asymmetric actor-critic whose critic reads the privileged state (``--critic-obs privileged``), with the exported
policy acting from the camera alone."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch
import torch.optim as optim

from agents.ppo import Agent, Args, main, ppo_update
from maniskill_irb120.policies.nets import random_shift

IMAGE = (84, 84, 4)


def images(n: int, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
    g = generator or torch.Generator().manual_seed(0)
    return dict(
        rgb=torch.randint(0, 256, (n, 84, 84, 3), dtype=torch.uint8, generator=g),
        depth=torch.randint(0, 3000, (n, 84, 84, 1), dtype=torch.int16, generator=g),
        state=torch.randn(n, 7, generator=g),
    )


# ----------------------------------------------------------------------------- --augment shift
def test_a_shift_keeps_shape_dtype_and_the_other_keys_and_no_padding_is_the_identity():
    obs = dict(images(6), privileged=torch.randn(6, 39))
    out = random_shift(obs, pad=4)
    for k in ("rgb", "depth"):
        assert out[k].shape == obs[k].shape and out[k].dtype == obs[k].dtype and out[k].is_contiguous()
    assert out["state"] is obs["state"] and out["privileged"] is obs["privileged"]  # not images: untouched
    same = random_shift(obs, pad=0)  # a shift of 0
    assert torch.equal(same["rgb"], obs["rgb"]) and torch.equal(same["depth"], obs["depth"])


def test_every_sample_moves_by_at_most_4_px_and_rgb_and_depth_by_the_same():
    """A marker pixel per sample, at a different place in each: after the shift it is within ±4 px of where it
    was, and the depth image's marker sits at the RGB one's pixel (one offset per sample, both images)."""
    n = 64
    rgb = torch.zeros(n, 84, 84, 3, dtype=torch.uint8)
    depth = torch.zeros(n, 84, 84, 1, dtype=torch.int16)
    ys, xs = torch.randint(10, 74, (n,)), torch.randint(10, 74, (n,))
    rgb[torch.arange(n), ys, xs] = 255
    depth[torch.arange(n), ys, xs] = 700
    out = random_shift(dict(rgb=rgb, depth=depth), generator=torch.Generator().manual_seed(1))
    moves = set()
    for i in range(n):
        r = torch.nonzero(out["rgb"][i, :, :, 0] == 255)
        d = torch.nonzero(out["depth"][i, :, :, 0] == 700)
        assert len(r) == 1 and torch.equal(r, d)
        dy, dx = int(r[0, 0] - ys[i]), int(r[0, 1] - xs[i])
        assert abs(dy) <= 4 and abs(dx) <= 4
        moves.add((dy, dx))
    assert len(moves) > 10  # one offset per sample, not one for the batch


def test_two_seeds_give_different_shifts_and_one_seed_the_same():
    obs = images(16)

    def shifted(seed: int) -> torch.Tensor:
        return random_shift(obs, generator=torch.Generator().manual_seed(seed))["rgb"]

    assert torch.equal(shifted(3), shifted(3))
    assert not torch.equal(shifted(3), shifted(4))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_shift_on_cuda_matches_the_cpu_one():
    obs = images(8)
    g = torch.Generator(device="cuda").manual_seed(5)
    out = random_shift({k: v.cuda() for k, v in obs.items()}, generator=g)
    g = torch.Generator(device="cuda").manual_seed(5)
    dx = torch.randint(0, 9, (8,), device="cuda", generator=g).cpu()
    dy = torch.randint(0, 9, (8,), device="cuda", generator=g).cpu()
    for i in range(8):
        rows, cols = (dy[i] - 4 + torch.arange(84)).clamp(0, 83), (dx[i] - 4 + torch.arange(84)).clamp(0, 83)
        assert torch.equal(out["rgb"][i].cpu(), obs["rgb"][i][rows][:, cols])


def test_the_update_trains_on_shifted_images_and_the_rollout_on_the_originals(monkeypatch):
    """--augment shift: ppo_update shifts each minibatch's images (the stored batch stays as it was); none: no shift."""
    import agents.ppo as ppo

    calls = []
    monkeypatch.setattr(ppo, "random_shift", lambda obs: calls.append(obs["rgb"].shape[0]) or random_shift(obs))
    torch.manual_seed(0)
    agent = Agent(IMAGE, 7, 5)
    batch = batch_for(agent, 16)
    before = batch["obs"]["rgb"].clone()
    args = Args(num_minibatches=4, update_epochs=2, target_kl=None, augment="shift")
    ppo_update(agent, optim.Adam(agent.parameters(), lr=1e-4), batch, args)
    assert calls == [4] * 8 and torch.equal(batch["obs"]["rgb"], before)
    calls.clear()
    ppo_update(agent, optim.Adam(agent.parameters(), lr=1e-4), batch, Args(num_minibatches=4, update_epochs=1))
    assert calls == []


def batch_for(agent: Agent, n: int, privileged: int = 0) -> dict:
    obs = images(n)
    if privileged:
        obs["privileged"] = torch.randn(n, privileged)
    with torch.no_grad():
        actions, logprobs, _, values = agent.get_action_and_value(obs)
    returns = torch.randn(n)
    return dict(
        obs=obs,
        actions=actions,
        logprobs=logprobs,
        values=values.view(-1),
        returns=returns,
        advantages=returns - values.view(-1),
    )


# ----------------------------------------------------------------------------- --critic-obs privileged
def test_the_privileged_critic_reads_only_the_privileged_state_and_the_actor_never_does():
    torch.manual_seed(0)
    agent = Agent(IMAGE, 7, 5, critic_obs="privileged", privileged_dim=39)
    obs = dict(images(4), privileged=torch.randn(4, 39))
    value = agent.get_value(obs)
    _, _, _, value_too = agent.get_action_and_value(obs)
    assert value.shape == (4, 1) and torch.allclose(value, value_too)
    other = dict(images(4, torch.Generator().manual_seed(9)), privileged=obs["privileged"])
    assert torch.equal(agent.get_value(other), value)  # another image, the same privileged state: the same value
    camera = {k: v for k, v in obs.items() if k != "privileged"}
    action = agent.get_action(camera, deterministic=True)  # acts without the privileged state
    shuffled = dict(obs, privileged=torch.randn(4, 39) * 100)
    assert torch.equal(agent.get_action(shuffled, deterministic=True), action)  # and is not moved by it
    with pytest.raises(KeyError, match="no 'privileged' key"):
        agent.get_value(camera)
    sig = agent.signature()
    assert sig["critic_obs"] == "privileged" and sig["privileged_dim"] == 39
    assert "critic_obs" not in Agent(IMAGE, 7, 5).signature()  # the default's signature is the old one: old runs load
    with pytest.raises(ValueError, match="needs an image"):
        Agent(None, 7, 5, critic_obs="privileged", privileged_dim=39)
    with pytest.raises(ValueError, match="unknown critic_obs"):
        Agent(IMAGE, 7, 5, critic_obs="teacher")


def test_the_privileged_value_loss_trains_the_critic_and_leaves_the_encoder_to_the_policy():
    torch.manual_seed(0)
    agent = Agent(IMAGE, 7, 5, critic_obs="privileged", privileged_dim=12)
    batch = batch_for(agent, 16, privileged=12)
    encoder = {k: v.clone() for k, v in agent.encoder.state_dict().items()}
    critic = {k: v.clone() for k, v in agent.critic.state_dict().items()}
    args = Args(num_minibatches=2, update_epochs=2, target_kl=None)
    ppo_update(agent, optim.Adam(agent.parameters(), lr=1e-3), batch, args, critic_only=True)
    assert all(torch.equal(v, agent.encoder.state_dict()[k]) for k, v in encoder.items())  # the value loss alone
    assert any(not torch.equal(v, agent.critic.state_dict()[k]) for k, v in critic.items())
    ppo_update(agent, optim.Adam(agent.parameters(), lr=1e-3), batch, args)
    assert any(not torch.equal(v, agent.encoder.state_dict()[k]) for k, v in encoder.items())  # the policy's loss


def test_an_exported_asymmetric_policy_acts_from_the_camera_alone(tmp_path):
    from maniskill_irb120.policies import acting, read_policy_section
    from maniskill_irb120.policies.section import export_policy

    torch.manual_seed(0)
    agent = Agent(IMAGE, 7, 5, critic_obs="privileged", privileged_dim=39)
    agent.critic_norm.update(torch.randn(32, 39) * 3)
    from agents.ppo import save_checkpoint

    args = Args(critic_obs="privileged")
    ckpt = tmp_path / "latest.pt"
    save_checkpoint(ckpt, agent, optim.Adam(agent.parameters()), dict(env_steps=0, iteration=0), args)
    export_policy(ckpt, tmp_path / "policy.pt", "python -m agents.ppo --critic-obs privileged")
    section = read_policy_section(tmp_path / "policy.pt")
    camera = images(3)  # what a deployment has: rgb, depth, state
    assert torch.equal(acting(section)(camera), agent.get_action(camera, deterministic=True))
    assert acting(section, sampled=True)(camera).shape == (3, 5)


def test_the_privileged_key_is_the_state_observation_through_steps_resets_and_final_observations():
    """The training envs' ``privileged`` key is what ``--obs state`` observes, step for step (the same seed and
    actions), after an auto-reset too, and a truncated episode's final observation carries its last state's (what
    the critic bootstraps on); the single-env backend wraps it as the GPU one does (ManiSkillVectorEnv)."""
    from agents.common.envs import PrivilegedStateObs, vec_envs

    kw = dict(backend="inprocess", action_frame="tool", env_kwargs=dict(max_episode_steps=3))
    cam = vec_envs("GraspLift-IRB120-v1", "rgbd", 1, outer_wrappers=[PrivilegedStateObs], **kw)
    state = vec_envs("GraspLift-IRB120-v1", "state", 1, **kw)
    try:
        assert cam.single_observation_space["privileged"].shape == state.single_observation_space.shape
        a, b = cam.reset(seed=3)[0], state.reset(seed=3)[0]
        assert torch.allclose(a["privileged"], b, atol=1e-5)
        g = torch.Generator().manual_seed(0)
        for t in range(5):
            act = torch.rand(1, 5, generator=g) * 2 - 1
            a, _, _, trunc, info_a = cam.step(act)
            b, _, _, _, info_b = state.step(act)
            assert torch.allclose(a["privileged"], b, atol=1e-5)  # after the reset: the new episode's
            if t == 2:
                assert bool(trunc.all())
                final = info_a["final_observation"]["privileged"]
                assert torch.allclose(final, info_b["final_observation"], atol=1e-5)
                assert not torch.allclose(final, a["privileged"], atol=1e-5)
    finally:
        cam.close()
        state.close()


def test_a_camera_only_flag_with_state_obs_is_refused_in_one_line(refused):
    refused("agents.ppo", ["--obs", "state", "--augment", "shift"], "--augment shift is for a camera policy")
    refused(
        "agents.ppo", ["--obs", "state", "--critic-obs", "privileged"], "--critic-obs privileged is for a camera policy"
    )


def test_a_camera_only_flag_with_state_obs_exits_2_from_the_command_line():
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[2]
    run = subprocess.run(
        [sys.executable, "-m", "agents.ppo", "--obs", "state", "--critic-obs", "privileged"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=repo,
    )
    assert run.returncode == 2, run.stderr
    assert run.stderr.strip() == (
        "agents.ppo: error: --critic-obs privileged is for a camera policy (--obs rgbd); this run has --obs state"
    )


def test_the_training_pages_command_parses():
    """docs/training.md's command with both flags is one agents.ppo accepts (the test below runs it, small)."""
    import re
    import shlex

    from agents.common import cli

    page = (Path(__file__).resolve().parents[2] / "docs" / "training.md").read_text()
    found = re.findall(r"-m agents\.ppo ([^`\n]*--augment shift[^`\n]*)", page)
    assert len(found) == 1, found
    args = cli(Args, "agents.ppo", shlex.split(found[0]), one_line=True)
    assert (args.obs, args.augment, args.critic_obs) == ("rgbd", "shift", "privileged")


# ----------------------------------------------------------------------------- end to end
def saved_dim(result: dict) -> int:
    ckpt = torch.load(Path(result["run_dir"]) / "checkpoints" / "latest.pt", weights_only=False)
    return ckpt["signature"]["privileged_dim"]


def test_an_augmented_asymmetric_camera_run_trains_resumes_and_its_export_evaluates(
    tmp_path, monkeypatch, tiny_ppo_rgbd
):
    """--obs rgbd --augment shift --critic-obs privileged on GraspLift: an iteration on two CPU envs (5-step
    episodes: the critic bootstraps their truncated ends from the final observations' privileged states), a
    checkpoint, --resume (the checkpoint's flags rebuild the network), and the exported policy evaluated on envs
    with no privileged key."""
    from agents.common import args as common_args
    from maniskill_irb120.policies import acting, read_policy_section
    from maniskill_irb120.policies.section import export_policy

    args = tiny_ppo_rgbd(tmp_path, augment="shift", critic_obs="privileged")
    valued = []  # the batches the critic valued: the rollout's truncated ends, then its next observation
    get_value = Agent.get_value
    monkeypatch.setattr(Agent, "get_value", lambda self, obs: valued.append(obs["privileged"]) or get_value(self, obs))
    first = main(args)
    assert len(valued) == 2 and valued[0].shape == valued[1].shape == (2, saved_dim(first))
    latest = Path(first["run_dir"]) / "checkpoints" / "latest.pt"
    saved = torch.load(latest, weights_only=False)
    assert saved["args"]["augment"] == "shift" and saved["args"]["critic_obs"] == "privileged"
    assert saved["signature"]["critic_obs"] == "privileged" and saved["signature"]["privileged_dim"] > 0
    assert float(saved["model"]["critic_norm.count"]) == 16  # the privileged states of the rollout, recorded
    assert not torch.equal(valued[0], valued[1])  # the final observations' own, not the reset ones after them
    # --resume alone: the flags come back from the checkpoint
    resumed = common_args.cli(Args, "agents.ppo", ["--resume", str(latest), "--total-env-steps", "32"], one_line=True)
    assert resumed.augment == "shift" and resumed.critic_obs == "privileged"
    again = main(resumed)
    assert again["global_step"] == 32 and again["iterations_this_run"] == 1
    # the export acts from the camera: evaluated on envs that give rgb/depth/state only
    export_policy(latest, tmp_path / "policy.pt", "pytest")
    section = read_policy_section(tmp_path / "policy.pt")
    assert section["config"]["critic_obs"] == "privileged" and section["obs"] == "rgbd"
    from agents.common import held_out_evaluation

    ev_args = replace(args, eval_episodes=1)
    scored = held_out_evaluation(acting(section), ev_args, None, reward_mode="normalized_dense")
    assert scored["episodes"] == 1
    ev = main(replace(args, evaluate=True, checkpoint=latest, eval_episodes=1, capture_video=False))
    assert ev["episodes"] == 1
