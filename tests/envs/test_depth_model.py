"""The RealSense-like depth model (envs/depth_model.py): each effect on synthetic depth, seeded; then once through
a real env's observation."""

from __future__ import annotations

import ast
import inspect
from dataclasses import replace

import gymnasium as gym
import pytest
import torch

import maniskill_irb120  # noqa: F401
from maniskill_irb120.envs import depth_model
from maniskill_irb120.envs.depth_model import PRESETS, DepthModel
from maniskill_irb120.envs.randomization import Randomization

D435, D405 = PRESETS["d435"], PRESETS["d405"]
F_SIM = 42.0  # the hand camera's focal length: 84 px across 90 deg


def flat(z_mm: int, n: int = 4, size: int = 64) -> torch.Tensor:
    return torch.full((n, size, size, 1), z_mm, dtype=torch.int16)


def plane_and_box(box_mm: int, plane_mm: int = 400) -> torch.Tensor:
    d = flat(plane_mm, n=2, size=84)
    d[:, 30:50, 30:50] = box_mm
    return d


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def test_error_grows_with_the_square_of_the_distance():
    near = D435.apply(flat(1000), None, F_SIM, gen(1)).float() - 1000
    far = D435.apply(flat(2000), None, F_SIM, gen(2)).float() - 2000
    assert far.std() / near.std() == pytest.approx(4.0, rel=0.1)
    assert far.std() == pytest.approx(D435.rms_error_m(2.0) * 1000, rel=0.1)  # 15 mm at 2 m (Intel's formula)
    assert abs(float(far.mean())) < 1.0  # unbiased


def test_depths_snap_to_the_disparity_grid():
    exact = replace(D435, subpixel=0.0, edge_jump_m=10.0)
    z_in = torch.arange(1500, 2500, 7, dtype=torch.int16)  # one distance per env
    out = exact.apply(z_in.reshape(-1, 1, 1, 1).expand(-1, 4, 4, 1).contiguous(), None, F_SIM, gen())
    fb = exact.focal_px * exact.baseline_m
    k = torch.round(fb / (out.double() / 1000) / exact.subpixel_step)
    on_grid = 1000 * fb / (k * exact.subpixel_step)
    assert (out.double() - on_grid).abs().max() <= 0.5  # mm rounding of a grid depth
    assert (out[:, 0, 0, 0] != z_in).float().mean() > 0.5  # snapped, not passed through
    assert len(torch.unique(out)) < len(z_in)  # 1 m of 7 mm steps holds fewer grid depths (5-8 mm apart here)


def test_edges_and_the_shadow_on_the_left_of_a_near_object():
    out = D435.apply(plane_and_box(210), None, F_SIM, gen())[0, ..., 0]
    assert (out[30:50, 30] == 0).all() and (out[30:50, 49] == 0).all()  # the box's own rim
    assert (out[29, 30:50] == 0).all() and (out[50, 30:50] == 0).all()  # the plane beside it
    assert (out[31:49, 31:49] > 0).all()  # the box's face reads
    # shadow: the disparity difference 42 px * 0.05 m * (1/0.21 - 1/0.4) = 4.75 sim px, on the -u side only
    assert (out[32:48, 26:30] == 0).all() and (out[32:48, 25] > 0).all()
    assert (out[32:48, 51:55] > 0).all()
    # a far box casts a narrower shadow: 42 * 0.05 * (1/0.35 - 1/0.4) = 0.75 px, none beyond the edge
    assert (D435.apply(plane_and_box(350), None, F_SIM, gen())[0, 32:48, 25:29, 0] > 0).all()


def test_below_the_minimum_range_reads_nothing():
    assert (D435.apply(flat(150), None, F_SIM, gen()) == 0).all()  # D435 at 848x480: 0.195 m
    assert (D405.apply(flat(150), None, F_SIM, gen()) > 0).all()  # D405: 0.07 m
    assert (D405.apply(flat(60), None, F_SIM, gen()) == 0).all()
    assert (D405.apply(flat(600), None, F_SIM, gen()) == 0).all()  # beyond its 0.5 m


def test_dark_and_specular_pixels_drop_more():
    rgb = torch.full((4, 64, 64, 3), 128, dtype=torch.uint8)
    rgb[:, :, :20] = 0  # black
    rgb[:, :, 40:] = 255  # a saturated highlight
    out = D435.apply(flat(400), rgb, F_SIM, gen())[..., 0] == 0
    black, grey, white = out[:, :, :20].float().mean(), out[:, :, 22:38].float().mean(), out[:, :, 42:].float().mean()
    assert grey == 0
    assert black == pytest.approx(D435.dark_dropout, abs=0.05) and white == pytest.approx(0.5, abs=0.05)
    out405 = D405.apply(flat(400), rgb, F_SIM, gen())[..., 0] == 0  # no projector: more holes on black
    assert out405[:, :, :20].float().mean() > black + 0.2


def test_seeded_per_env_and_nothing_but_torch():
    d = flat(800)
    a, b = D435.apply(d, None, F_SIM, gen(7)), D435.apply(d, None, F_SIM, gen(7))
    assert torch.equal(a, b) and a.dtype == torch.int16 and a.shape == d.shape
    assert not torch.equal(a[0], a[1])  # each env draws its own noise
    assert not torch.equal(a, D435.apply(d, None, F_SIM, gen(8)))
    names = {n.id for n in ast.walk(ast.parse(inspect.getsource(depth_model))) if isinstance(n, ast.Name)}
    assert "np" not in names and "numpy" not in names  # the same code runs on a CUDA tensor


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="num_envs, H, W, 1"):
        D435.apply(torch.zeros(64, 64, dtype=torch.int16), None, F_SIM)
    with pytest.raises(ValueError, match="does not match depth"):
        D435.apply(flat(400), torch.zeros(4, 32, 32, 3, dtype=torch.uint8), F_SIM)
    with pytest.raises(ValueError, match="baseline_m must be > 0"):
        DepthModel("broken", baseline_m=0.0, focal_px=400.0)


def test_the_randomisation_field():
    assert Randomization.parse("depth_model=d435,depth_noise=1").depth_model == "d435"
    assert Randomization.from_any({"depth_model": "D405"}).depth_model == "d405"
    assert Randomization.parse("depth_model=off").active() == [] and Randomization().depth_model is None
    with pytest.raises(ValueError, match=r"one of \['d405', 'd435'\]"):
        Randomization.parse("depth_model=kinect")
    with pytest.raises(ValueError, match="a preset name"):
        Randomization(depth_model=3)


def test_through_an_env_the_depth_reads_zero_where_the_model_says():
    clean = gym.make("TableClearing-IRB120-v1", obs_mode="rgbd")
    real = gym.make("TableClearing-IRB120-v1", obs_mode="rgbd", randomization="depth_model=d435")
    clean.reset(seed=5)
    real.reset(seed=5)
    act = torch.tensor([0.2, 0.0, -0.3, 0.0, 1.0])
    truth = clean.step(act)[0]["sensor_data"]["hand_camera"]
    seen = real.step(act)[0]["sensor_data"]["hand_camera"]["depth"][0, ..., 0]
    clean.close()
    real.close()
    z, valid = truth["depth"][0, ..., 0].float() / 1000, truth["depth"][0, ..., 0] > 0
    near = valid & (z < D435.min_m - 0.005)  # the gripper's fingers, a few cm from the lens
    geometry = D435._edges(z[None], valid[None])[0] | D435._shadow(z[None], valid[None], torch.tensor(F_SIM), F_SIM)[0]
    assert near.any() and (seen[near] == 0).all()
    assert geometry.any() and (seen[geometry] == 0).all()
    rest = valid & ~near & ~geometry & (z > D435.min_m + 0.01)
    read = seen[rest] > 0
    assert read.float().mean() > 0.8  # the table mostly reads, within the model's millimetres
    assert (seen[rest][read].float() - truth["depth"][0, ..., 0][rest][read].float()).abs().max() <= 5


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (on a GPU machine: pytest -m gpu)")
def test_cpu_physics_with_cuda_rendering_takes_the_depth_randomisation():
    """On a GPU machine the CPU sim renders on CUDA, so the frame is a CUDA tensor while the randomisation's
    generator lives on the sim's CPU; the H200's first randomised camera run failed here ("Expected a 'cuda'
    device type for generator")."""
    on_cuda = D435.apply(flat(800).cuda(), None, F_SIM, gen(7))
    same = on_cuda.cpu() == D435.apply(flat(800), None, F_SIM, gen(7))  # the same draws (rounding may differ)
    assert on_cuda.device.type == "cuda" and same.float().mean() > 0.99
    env = gym.make(
        "TableClearing-IRB120-v1",
        obs_mode="rgbd",
        sim_backend="cpu",
        render_backend="gpu",
        randomization="depth_model=d435,depth_noise=0:5,depth_dropout=0:0.06",
    )
    env.reset(seed=5)
    depth = env.step(torch.tensor([0.2, 0.0, -0.3, 0.0, 1.0]))[0]["sensor_data"]["hand_camera"]["depth"]
    env.close()
    assert depth.shape == (1, 84, 84, 1) and (depth > 0).any()


def test_a_choice_of_depth_models_is_parsed_and_checked():
    assert Randomization.parse("depth_model=d435|D405|off").depth_model == ("d435", "d405", "off")
    assert Randomization.parse("depth_model=d435|d405").active() == ["depth_model"]
    with pytest.raises(ValueError, match="each model once"):
        Randomization.parse("depth_model=d435|d435")
    with pytest.raises(ValueError, match=r"one of \['d405', 'd435'\]"):
        Randomization.parse("depth_model=d435|kinect")


def test_each_episode_draws_one_model_of_the_choice_and_reads_as_that_model_alone():
    """``depth_model=d435|off``: an episode that drew ``off`` sees the clean depth, one that drew ``d435`` exactly
    what ``depth_model=d435`` alone gives on the same seed (the choice is drawn after every other stream)."""
    act = torch.tensor([0.2, 0.0, -0.3, 0.0, 1.0])
    envs = {
        spec: gym.make("TableClearing-IRB120-v1", obs_mode="rgbd", randomization=spec)
        for spec in ("", "depth_model=d435", "depth_model=d435|off")
    }
    drawn_models = set()
    try:
        for seed in range(8):
            seen = {}
            for spec, env in envs.items():
                env.reset(seed=seed)
                seen[spec] = env.step(act)[0]["sensor_data"]["hand_camera"]["depth"].clone()
            k = int(envs["depth_model=d435|off"].unwrapped.randomization_draws["depth_model"][0])
            drawn_models.add(k)
            same_as = "depth_model=d435" if k == 0 else ""
            assert torch.equal(seen["depth_model=d435|off"], seen[same_as]), (seed, k)
            assert not torch.equal(seen["depth_model=d435"], seen[""])
    finally:
        for env in envs.values():
            env.close()
    assert drawn_models == {0, 1}  # both models drawn in 8 episodes
