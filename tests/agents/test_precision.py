"""--precision: bf16 autocast for the learner's updates, refused where it would be emulated; the weights, the
losses and the keypoints stay float32, and a bf16 round learns what an fp32 round learns."""

from __future__ import annotations

import pytest
import torch

from agents.common import Dataset, autocast, precision, resolve_precision
from agents.dagger import Args, train_round
from maniskill_irb120.policies.nets import DeterministicActor, SpatialSoftmax

CPU = torch.device("cpu")
needs_bf16 = pytest.mark.skipif(not precision.native_bf16(CPU), reason="this CPU has no native bfloat16")


def test_unknown_and_emulated_precisions_are_refused(monkeypatch):
    with pytest.raises(ValueError, match="'fp16' is not one of"):
        resolve_precision("fp16", CPU)
    monkeypatch.setattr(precision, "native_bf16", lambda device: False)
    with pytest.raises(ValueError, match="no native bfloat16"):
        resolve_precision("bf16", CPU)
    assert resolve_precision("auto", CPU) == "fp32"
    monkeypatch.setattr(precision, "native_bf16", lambda device: True)
    assert resolve_precision("auto", CPU) == "bf16"
    assert resolve_precision("auto", torch.device("cuda")) == "fp32"  # measured slower on a GPU (RESULTS.md)
    assert resolve_precision("bf16", torch.device("cuda")) == "bf16"
    with pytest.raises(ValueError, match="not resolved"):
        autocast("auto", CPU)


@needs_bf16
def test_keypoints_and_proprioception_stay_float32_under_autocast():
    torch.manual_seed(0)
    ss = SpatialSoftmax(21, 21)
    x = torch.randn(3, 8, 21, 21)
    with autocast("bf16", CPU):
        inside = ss(x.bfloat16())
        conv = torch.nn.functional.conv2d(x, torch.randn(4, 8, 1, 1))
    assert conv.dtype == torch.bfloat16  # autocast is on ...
    assert inside.dtype == torch.float32  # ... and the coordinates opt out of it
    assert torch.allclose(inside, ss(x.bfloat16().float()), atol=1e-6)
    policy = DeterministicActor((42, 42, 4), 6, 5, encoder="keypoints")
    obs = dict(
        rgb=torch.randint(0, 256, (2, 42, 42, 3), dtype=torch.uint8),
        depth=torch.randint(200, 900, (2, 42, 42, 1), dtype=torch.int16),
        state=torch.randn(2, 6),
    )
    with autocast("bf16", CPU):
        feats = policy.features(obs)
    assert feats.dtype == torch.float32
    n = policy.encoder.out_dim - 256  # the keypoints, then the proprioception's 256 features: those exact
    assert torch.equal(feats[:, n:], policy.features(obs)[:, n:])


@needs_bf16
def test_a_bf16_round_learns_like_an_fp32_round_and_keeps_fp32_weights():
    """The same camera data and seed: the BC loss falls as far under bf16 autocast as under fp32."""
    g = torch.Generator().manual_seed(0)
    n = 96
    rgb = torch.randint(0, 256, (n, 42, 42, 3), dtype=torch.uint8, generator=g)
    depth = torch.randint(200, 900, (n, 42, 42, 1), dtype=torch.int16, generator=g)
    state = torch.randn(n, 6, generator=g)
    target = torch.tanh(state[:, :5] + rgb[:, 20, 20, :1].float() / 128 - 1)  # needs the image and the state
    data = Dataset(n)
    data.add(dict(rgb=rgb, depth=depth, state=state), target)
    args = Args(obs="rgbd", encoder="keypoints", updates_per_round=60, batch_size=32)
    final = {}
    for prec in ("fp32", "bf16"):
        torch.manual_seed(1)
        policy = DeterministicActor((42, 42, 4), 6, 5, encoder="keypoints")
        opt = torch.optim.AdamW(policy.parameters(), lr=1e-3)
        first = train_round(policy, opt, data, Args(obs="rgbd", updates_per_round=1, batch_size=n), CPU)["bc"]
        train_round(policy, opt, data, args, CPU, precision=prec)
        final[prec] = train_round(policy, opt, data, Args(obs="rgbd", updates_per_round=1, batch_size=n), CPU)["bc"]
        assert final[prec] < 0.7 * first, (prec, first, final[prec])
        assert all(p.dtype == torch.float32 for p in policy.parameters())
    assert final["bf16"] < 1.3 * final["fp32"] + 0.01, final
