"""PPO's ``--encoder keypoints`` (issue 92): DAgger's KeypointCNN under PPO's heads, recorded in the checkpoint's
signature only when it is not the Nature CNN (older checkpoints load as they are), rebuilt by ``--resume``,
``--evaluate`` and an exported policy."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import torch.optim as optim

from agents.ppo import Agent, Args, load_checkpoint, main, ppo_update, save_checkpoint
from maniskill_irb120.policies.nets import DeterministicActor, KeypointCNN, NatureCNN

IMAGE = (84, 84, 4)


def images(n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return dict(
        rgb=torch.randint(0, 256, (n, 84, 84, 3), dtype=torch.uint8, generator=g),
        depth=torch.randint(0, 3000, (n, 84, 84, 1), dtype=torch.int16, generator=g),
        state=torch.randn(n, 7, generator=g),
    )


def test_the_flag_builds_dagger_s_keypoint_encoder_and_only_then_signs_it():
    torch.manual_seed(0)
    agent = Agent(IMAGE, 7, 5, obs_norm=True, encoder="keypoints")
    assert type(agent.encoder) is KeypointCNN
    dagger = DeterministicActor(IMAGE, 7, 5, encoder="keypoints").encoder  # DAgger's --encoder keypoints
    assert {k: v.shape for k, v in agent.encoder.state_dict().items()} == {
        k: v.shape for k, v in dagger.state_dict().items()
    }
    assert agent.actor_mean[0].in_features == agent.critic[0].in_features == KeypointCNN(IMAGE, 7).out_dim
    assert agent.signature()["encoder"] == "keypoints"
    depth = Agent(IMAGE, 7, 5, obs_norm=True, encoder="keypoints-depth")  # the same encoder as DAgger's too
    assert {k: v.shape for k, v in depth.encoder.state_dict().items()} == {
        k: v.shape for k, v in DeterministicActor(IMAGE, 7, 5, encoder="keypoints-depth").encoder.state_dict().items()
    }
    assert depth.actor_mean[0].in_features == KeypointCNN(IMAGE, 7).out_dim + 32
    assert depth.signature()["encoder"] == "keypoints-depth"
    nature = Agent(IMAGE, 7, 5, obs_norm=True)
    assert type(nature.encoder) is NatureCNN and "encoder" not in nature.signature()  # the signature it always had
    with pytest.raises(ValueError, match="unknown encoder"):
        Agent(IMAGE, 7, 5, encoder="resnet")
    with pytest.raises(ValueError, match="reads the camera"):
        Agent(None, 7, 5, encoder="keypoints")
    with pytest.raises(ValueError, match="reads the camera"):
        Agent(None, 7, 5, state_net="mlp", encoder="keypoints")


def test_a_keypoint_residual_s_base_is_a_keypoint_dagger_policy():
    agent = Agent(IMAGE, 7, 5, residual=True, encoder="keypoints")
    assert type(agent.base.encoder) is KeypointCNN
    base = DeterministicActor(IMAGE, 7, 5, encoder="keypoints")
    own = ("residual", "state_net", "obs_norm", "logstd")  # what agents.ppo.agent_for leaves out of the match
    assert base.signature() == {k: v for k, v in agent.signature().items() if k not in own}
    agent.base.load_state_dict(base.state_dict())  # a keypoint DAgger checkpoint's weights fit


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_the_update_trains_the_keypoint_encoder(precision):
    """One PPO update (both precisions: ``fast+keypoints`` is bf16) moves the convolutions and the spatial
    softmax's temperature, and its losses are finite."""
    from agents.common.precision import native_bf16

    if precision == "bf16" and not native_bf16(torch.device("cpu")):
        pytest.skip("no native bf16 on this CPU")
    torch.manual_seed(1)
    agent = Agent(IMAGE, 7, 5, obs_norm=True, encoder="keypoints")
    n = 16
    obs = images(n, seed=2)
    with torch.no_grad():
        actions, logp, _, value = agent.get_action_and_value(obs)
    batch = dict(
        obs=obs,
        actions=actions,
        logprobs=logp,
        advantages=torch.randn(n, generator=torch.Generator().manual_seed(3)),
        returns=torch.randn(n),
        values=value.view(-1),
    )
    before = {k: v.clone() for k, v in agent.encoder.state_dict().items()}
    args = Args(num_minibatches=2, update_epochs=2, precision=precision, target_kl=None)
    stats = ppo_update(agent, optim.Adam(agent.parameters(), lr=1e-3), batch, args)
    assert all(torch.isfinite(torch.tensor(v)) for v in stats.values()), stats
    after = agent.encoder.state_dict()
    assert not torch.equal(before["cnn.0.weight"], after["cnn.0.weight"])
    assert not torch.equal(before["keypoints.log_temperature"], after["keypoints.log_temperature"])


def test_an_exported_keypoint_policy_acts_as_the_agent_and_a_nature_run_refuses_its_checkpoint(tmp_path):
    from maniskill_irb120.policies import acting, policy_module, read_policy_section
    from maniskill_irb120.policies.section import export_policy

    torch.manual_seed(0)
    agent = Agent(IMAGE, 7, 5, obs_norm=True, encoder="keypoints")
    agent.norm.update(torch.randn(64, 7) * 2 + 1)  # the running normaliser travels with the export
    args = Args(encoder="keypoints", obs_norm=True)
    ckpt = tmp_path / "latest.pt"
    save_checkpoint(ckpt, agent, optim.Adam(agent.parameters()), dict(env_steps=0, iteration=0), args)
    export_policy(ckpt, tmp_path / "policy.pt", "python -m agents.ppo --encoder keypoints")
    section = read_policy_section(tmp_path / "policy.pt")
    assert section["config"]["encoder"] == "keypoints"
    assert type(policy_module(section).encoder) is KeypointCNN
    camera = images(4, seed=5)
    agent.eval()
    assert torch.equal(acting(section)(camera), agent.get_action(camera, deterministic=True))
    sample = acting(section, sampled=True)  # built first: building initialises weights from torch's RNG
    torch.manual_seed(7)
    sampled = sample(camera)
    torch.manual_seed(7)
    assert torch.equal(sampled, agent.get_action(camera))
    # a Nature CNN agent refuses it, naming both signatures (and the keypoint agent loads it)
    with pytest.raises(ValueError, match="encoder 'keypoints' in the checkpoint"):
        load_checkpoint(ckpt, Agent(IMAGE, 7, 5, obs_norm=True), args)
    load_checkpoint(ckpt, Agent(IMAGE, 7, 5, obs_norm=True, encoder="keypoints"), args)


def test_a_checkpoint_from_before_the_flag_loads_as_the_nature_cnn(tmp_path):
    """A PPO checkpoint written before ``encoder`` existed (format version 1: its signature lacks the key, and the
    options added since) is migrated and rebuilt as the Nature CNN, by the trainer and by the export alike."""
    from agents.common.checkpoints import load_torch
    from agents.ppo import FORMAT
    from maniskill_irb120.policies import acting, section_of

    torch.manual_seed(0)
    agent = Agent(IMAGE, 7, 5)
    old = dict(
        format=FORMAT,
        model=agent.state_dict(),
        signature=dict(image_shape=list(IMAGE), state_dim=7, action_dim=5),  # a version-1 signature
        args=dict(obs="rgbd"),
        counters=dict(global_step=0, iteration=0),
    )
    torch.save(old, tmp_path / "old.pt")
    ckpt = load_torch(tmp_path / "old.pt", FORMAT, "agents.ppo")
    assert "encoder" not in ckpt["signature"]
    load_checkpoint(tmp_path / "old.pt", (nature := Agent(IMAGE, 7, 5)), Args(), ckpt)
    camera = images(2)
    assert torch.equal(acting(section_of(torch.load(tmp_path / "old.pt", weights_only=False)))(camera),
                       nature.eval().get_action(camera, deterministic=True))  # fmt: skip
    with pytest.raises(ValueError, match="its networks differ from this run"):
        load_checkpoint(tmp_path / "old.pt", Agent(IMAGE, 7, 5, encoder="keypoints"), Args(), ckpt)


def test_bad_encoder_flags_are_refused_in_one_line(refused):
    refused("agents.ppo", ["--obs", "state", "--encoder", "keypoints"], "--encoder keypoints is for a camera policy")


def test_an_unknown_encoder_exits_2_from_the_command_line():
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[2]
    argv = [sys.executable, "-m", "agents.ppo", "--encoder", "resnet"]
    run = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=repo)
    assert run.returncode == 2, run.stderr
    err = run.stderr.strip()
    assert len(err.splitlines()) == 1 and "--encoder" in err and "resnet" in err, err


def test_a_keypoint_camera_run_trains_resumes_and_evaluates(tmp_path, tiny_ppo_rgbd):
    """--obs rgbd --encoder keypoints on GraspLift: an iteration on two CPU envs, a checkpoint that signs the
    encoder, --resume alone (the flag comes back from the checkpoint), and --evaluate without the flag (the
    checkpoint's signature rebuilds the network)."""
    from agents.common import args as common_args

    args = tiny_ppo_rgbd(tmp_path, encoder="keypoints", obs_norm=True)
    torch.manual_seed(0)
    first = main(args)
    assert first["global_step"] == 16
    latest = Path(first["run_dir"]) / "checkpoints" / "latest.pt"
    saved = torch.load(latest, weights_only=False)
    assert saved["args"]["encoder"] == "keypoints" and saved["signature"]["encoder"] == "keypoints"
    assert "encoder.keypoints.log_temperature" in saved["model"]
    resumed = common_args.cli(Args, "agents.ppo", ["--resume", str(latest), "--total-env-steps", "32"], one_line=True)
    assert resumed.encoder == "keypoints"
    again = main(resumed)
    assert again["global_step"] == 32 and again["iterations_this_run"] == 1
    argv = f"--env-id GraspLift-IRB120-v1 --evaluate --checkpoint {latest} --eval-episodes 1 --obs-norm"
    argv += f" --env-kwargs max_episode_steps 5 --no-capture-video --no-progress --runs-dir {tmp_path}"
    ev = common_args.cli(Args, "agents.ppo", argv.split(), one_line=True)
    assert ev.encoder == "nature"  # not given (--obs-norm must be, as for any checkpoint): the signature says keypoints
    scored = main(ev)
    assert scored["episodes"] == 1
