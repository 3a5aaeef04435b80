"""A checkpoint's policy section: each kind's module comes back from it alone and acts as the trained one did,
a checkpoint from before sections existed reads the same way, and misuse is named."""

from __future__ import annotations

import pytest
import torch

from maniskill_irb120.policies import acting, policy_module, policy_section, read_policy_section, section_of
from maniskill_irb120.policies.nets import DeterministicActor
from maniskill_irb120.policies.ppo import Agent
from maniskill_irb120.policies.sac import SAC

ENV = "TableClearing-IRB120-v1"
OBS = {"state": torch.randn(3, 7)}


def modules():
    torch.manual_seed(0)
    ppo = Agent(None, 7, 5)
    dagger = DeterministicActor(None, 7, 5)
    sac = SAC(None, 7, 5, 0.1, reference=True)
    return dict(
        ppo=(ppo, dict(ppo.signature(), init_logstd=ppo.init_logstd), "maniskill_irb120.ppo/1"),
        dagger=(dagger, dagger.signature(), "maniskill_irb120.dagger/1"),
        sac=(sac, dict(sac.signature(), init_alpha=1.0), "maniskill_irb120.sac/1"),
    )


@pytest.mark.parametrize("kind", ["ppo", "dagger", "sac"])
def test_a_section_and_a_legacy_checkpoint_act_like_the_module(kind, tmp_path):
    module, config, fmt = modules()[kind]
    module.eval()
    section = policy_section(kind, module, config, env_id=ENV, obs="state", action_frame="world", init_std=0.1)
    path = tmp_path / "ckpt.pt"
    torch.save(dict(format=fmt, model=module.state_dict(), policy=section), path)
    legacy = dict(format=fmt, model=module.state_dict(), signature=module.signature(), args=dict(env_id=ENV))
    with torch.no_grad():
        expected = acting(section)(OBS)
        assert torch.equal(acting(read_policy_section(path))(OBS), expected)
        assert torch.equal(acting(section_of(legacy))(OBS), expected)
    assert type(policy_module(section)) is type(module) and not policy_module(section).training
    assert section_of(legacy)["stochastic"] == (kind != "dagger")


def test_misuse_is_named(tmp_path):
    dagger, config, _ = modules()["dagger"]
    with pytest.raises(ValueError, match="unknown policy kind"):
        policy_section("bc", dagger, config, env_id=ENV, obs="state", action_frame="world")
    with pytest.raises(TypeError, match="DeterministicActor"):
        policy_section("dagger", Agent(None, 7, 5), config, env_id=ENV, obs="state", action_frame="world")
    section = policy_section("dagger", dagger, config, env_id=ENV, obs="state", action_frame="world")
    with pytest.raises(ValueError, match="deterministic"):
        acting(section, sampled=True)
    with pytest.raises(ValueError, match="none of"):
        section_of(dict(format="someone-else/1"))
    with pytest.raises(FileNotFoundError):
        read_policy_section(tmp_path / "missing.pt")


def test_export_keeps_the_policy_alone_and_it_acts_the_same(tmp_path):
    from maniskill_irb120.cli import main as cli
    from maniskill_irb120.policies.section import export_policy, section_sha256

    dagger, config, fmt = modules()["dagger"]
    dagger.eval()
    section = policy_section("dagger", dagger, config, env_id=ENV, obs="state", action_frame="world")
    src, dst = tmp_path / "latest.pt", tmp_path / "out" / "policy.pt"
    optimiser_state = {"exp_avg": torch.randn(1_000_000)}  # what a trainer's checkpoint also carries
    torch.save(dict(format=fmt, policy=section, optimizer=optimiser_state), src)
    meta = export_policy(src, dst, "python -m agents.dagger --obs state --seed 7")
    assert meta["bytes"] < src.stat().st_size / 2 and meta["kind"] == "dagger"
    saved = torch.load(dst, weights_only=False)
    assert saved["command"] == "python -m agents.dagger --obs state --seed 7" and "optimizer" not in saved
    with torch.no_grad():
        assert torch.equal(acting(read_policy_section(dst))(OBS), acting(section)(OBS))
    # the export is the same policy by its hash (sim2real_gap --reuse reads a checkpoint's rows for it), in bf16 too
    assert section_sha256(read_policy_section(dst)) == section_sha256(read_policy_section(src))
    half = dict(section, state_dict={k: v.to(torch.bfloat16) for k, v in section["state_dict"].items()})
    assert section_sha256(half) == section_sha256(dict(half)) != section_sha256(section)
    nudged = {k: v.clone() for k, v in section["state_dict"].items()}
    next(iter(nudged.values())).view(-1)[0] += 1e-6  # one weight moved: another policy
    assert section_sha256(dict(section, state_dict=nudged)) != section_sha256(section)
    assert section_sha256(dict(section, obs="rgbd")) != section_sha256(section)  # a setting it acts by, too
    with pytest.raises(ValueError, match="--command"):
        export_policy(src, dst, " ")
    assert cli(["export-policy", "--checkpoint", str(tmp_path / "no.pt"), "--out", str(dst), "--command", "x"]) == 2


def test_state_norm_zeroes_what_never_varied_and_scales_the_rest():
    """A dimension constant in the fitting data (axis 4 in the sim) must not amplify a real robot's 0.02° on it."""
    from maniskill_irb120.policies.nets import StateNorm

    torch.manual_seed(0)
    data = torch.randn(500, 3) * torch.tensor([0.5, 1e-5, 0.02])  # a joint, a constant axis, a gripper opening
    norm = StateNorm(3)
    norm.fit(data)
    real = torch.tensor([[0.5, 3.5e-4, 0.02]])  # the constant axis off by 0.02 degrees
    out = norm({"state": real})["state"][0]
    assert out[1] == 0.0 and torch.isfinite(out).all()
    expected = (real[0] - data.mean(0)) / data.std(0)
    torch.testing.assert_close(out[[0, 2]], expected[[0, 2]], rtol=1e-4, atol=1e-6)
    assert norm.std[1] == float("inf")


def test_every_committed_policy_is_small_and_says_how_it_was_trained():
    """issue 30: the table's checkpoints are committed (each <= 5 MB) with the command that trained them, and load
    as the benchmarks load them"""
    from pathlib import Path

    committed = sorted((Path(__file__).resolve().parents[2] / "benchmarks/results/policies").glob("*.pt"))
    assert committed
    for path in committed:
        assert path.stat().st_size <= 5_000_000, path.name
        saved = torch.load(path, weights_only=False)
        assert "agents." in saved["command"] or "benchmarks/learning.py" in saved["command"], path.name
        module = policy_module(read_policy_section(path))
        assert sum(p.numel() for p in module.parameters()) > 0 and not module.training, path.name
