"""Domain randomisation (envs/randomization.py): each parameter changes what it should, nothing changes when
it is off, draws follow the seed, bad specs are named."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import sapien
import torch

import maniskill_irb120  # noqa: F401
from maniskill_irb120.envs import appearance
from maniskill_irb120.envs.randomization import Randomization

ENV_ID = "TableClearing-IRB120-v1"
SHIFT = (
    "camera_pos=0.01;0;0,camera_rot=0;0;10,camera_fov=70,light=0.5,color=0.3,"
    "object_size=1.2,object_mass=0.5,object_friction=0.4"
)


def make(spec=None, obs_mode="rgbd", **kw):
    return gym.make(ENV_ID, obs_mode=obs_mode, randomization=spec, **kw)


@pytest.fixture(scope="module")
def pair():
    nominal, shifted = make(), make(SHIFT)
    yield nominal, shifted
    nominal.close()
    shifted.close()


def test_off_is_bit_identical():
    a, b = make(None, "state", render_backend="none"), make(Randomization(), "state", render_backend="none")
    oa, _ = a.reset(seed=3)
    ob, _ = b.reset(seed=3)
    for t in range(5):
        act = torch.tensor([0.3, -0.2, 0.1 * t, 0.2, 1.0])
        oa, ra, *_ = a.step(act)
        ob, rb, *_ = b.step(act)
        assert torch.equal(oa, ob) and torch.equal(ra, rb)
    assert b.unwrapped.randomization_draws == {} and b.unwrapped.randomization.active() == []


def test_camera_mount_and_field_of_view(pair):
    nominal, shifted = pair
    nominal.reset(seed=0)
    obs, _ = shifted.reset(seed=0)
    cam = shifted.unwrapped._sensors["hand_camera"].camera._render_cameras[0]
    np.testing.assert_allclose(cam.local_pose.p, [-0.02, 0.0, 0.02], atol=1e-6)
    angle = 2 * math.degrees(math.acos(min(1.0, abs(cam.local_pose.q[0]))))
    assert angle == pytest.approx(10.0, abs=1e-3)
    fx = float(obs["sensor_param"]["hand_camera"]["intrinsic_cv"][0, 0, 0])
    assert fx == pytest.approx(42 / math.tan(math.radians(35)), rel=1e-3)  # 84 px across 70 deg
    nominal_cam = nominal.unwrapped._sensors["hand_camera"].camera._render_cameras[0]
    np.testing.assert_allclose(nominal_cam.local_pose.p, [-0.03, 0.0, 0.02], atol=1e-6)
    assert nominal_cam.fovy == pytest.approx(math.pi / 2)


def test_light_and_colour_change_the_image(pair):
    nominal, shifted = pair
    o_nom, _ = nominal.reset(seed=1)
    o_shift, _ = shifted.reset(seed=1)
    assert (
        o_shift["sensor_data"]["hand_camera"]["rgb"].float().mean()
        < 0.8 * o_nom["sensor_data"]["hand_camera"]["rgb"].float().mean()
    )
    body = shifted.unwrapped.obj._objs[0].find_component_by_type(sapien.render.RenderBodyComponent)
    jitter = np.array(body.render_shapes[0].material.base_color[:3]) - [0.8, 0.1, 0.1]  # the object's red
    assert 0 < np.abs(jitter).max() <= 0.3 + 1e-6
    draws = shifted.unwrapped.randomization_draws
    assert float(draws["light"][0]) == 0.5 and "color_source_tray" in draws


def _table_rows(rgb: torch.Tensor) -> np.ndarray:
    """The top rows of the hand camera's frame at the start pose: the table beyond the trays."""
    return rgb[0, :10].float().numpy()


def test_textures_colours_and_materials_per_surface_follow_the_seed(pair):
    """A procedural texture on the table shows as a pattern where the nominal table is one flat colour; the same
    seed draws the same surfaces, another seed others; the material terms are the drawn ones."""
    nominal, textured = pair[0], make("texture=1,color=0.2,roughness=0.2:0.8,specular=0.3")  # the module's nominal
    flat = _table_rows(nominal.reset(seed=0)[0]["sensor_data"]["hand_camera"]["rgb"])
    frames = [textured.reset(seed=s)[0]["sensor_data"]["hand_camera"]["rgb"] for s in (0, 1, 0)]
    u = textured.unwrapped
    assert flat.std(axis=(0, 1)).max() < 2.0  # a flat colour, lit evenly
    assert _table_rows(frames[0]).std(axis=(0, 1)).max() > 4.0  # a pattern
    assert torch.equal(frames[0], frames[2]) and not torch.equal(frames[0], frames[1])
    assert float(u.randomization_draws["texture_table"][0]) == 1.0
    body = u.table_scene.table._objs[0].find_component_by_type(sapien.render.RenderBodyComponent)
    mat = body.render_shapes[0].material
    assert mat.base_color_texture is not None and 0.2 <= mat.roughness <= 0.8
    assert mat.specular == pytest.approx(0.3)
    # what was drawn is recorded with it: the surface's colour as its material holds it, its pattern and contrast
    assert np.allclose(u.randomization_draws["rgb_table"][0].numpy(), mat.base_color[:3], atol=1e-6)
    assert int(u.randomization_draws["pattern_table"][0]) in range(len(appearance.PATTERNS))
    assert 0.15 <= float(u.randomization_draws["contrast_table"][0]) <= 0.6
    # each env's surfaces are built with materials of their own (a GPU-batched scene shares a builder's otherwise)
    assert u.own_materials and not nominal.unwrapped.own_materials
    assert len(u.table_scene.table._objs) == u.num_envs
    textured.close()


def test_object_color_jitters_the_objects_alone_and_off_leaves_every_draw_as_it_was():
    """``object_color`` moves the task's object's colour by its own range while the scene keeps ``color``'s; at the
    same amplitude as ``color`` it draws exactly what ``color`` alone draws (the same stream), so adding the field
    changed no earlier run's scenes."""
    seeds = range(6)

    def draws(spec):
        env = make(spec, obs_mode="state")
        try:
            out = []
            for seed in seeds:
                env.reset(seed=seed)
                out.append({k: v[0].clone() for k, v in env.unwrapped.randomization_draws.items()})
            return out
        finally:
            env.close()

    plain, same = draws("color=0.2,texture=0.5"), draws("color=0.2,texture=0.5,object_color=0.2")
    for a, b in zip(plain, same):
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    wide = draws("color=0.0,object_color=0.6")
    jitters = torch.stack([d["color_object"] for d in wide])
    assert jitters.abs().max() > 0.3 and jitters.abs().max() <= 0.6  # beyond color=0.3, within its own range
    for d in wide:
        assert all(torch.equal(d["color_" + s], torch.zeros(3)) for s in ("table", "source_tray", "dest_tray"))
    with pytest.raises(ValueError, match="object_color=-0.1: must be >= 0"):
        Randomization(object_color=-0.1)


def test_texture_probability_zero_keeps_the_plain_surfaces():
    env = make("texture=0.0,color=0.1")
    env.reset(seed=3)
    u = env.unwrapped
    for actor in u.scene_actors:
        body = actor._objs[0].find_component_by_type(sapien.render.RenderBodyComponent)
        assert all(shape.material.base_color_texture is None for shape in body.render_shapes)
    assert float(u.randomization_draws["texture_table"][0]) == 0.0
    assert float(u.randomization_draws["pattern_table"][0]) == -1.0
    env.close()


def test_scene_meshes_carry_planar_texture_coordinates():
    from maniskill_irb120.robot.description import TEXTURE_TILE_M, merged_box_mesh

    text = open(merged_box_mesh([((0.2, 0.1, 0.05), (0.0, 0.0, 0.0))])).read().splitlines()
    uv = np.array([[float(x) for x in line.split()[1:]] for line in text if line.startswith("vt ")])
    assert len(uv) == 24 and sum(line.startswith("f ") for line in text) == 12
    assert np.abs(uv).max() == pytest.approx(0.2 / TEXTURE_TILE_M)  # metres in tiles


def test_object_size_mass_and_friction(pair):
    nominal, shifted = pair
    u, n = shifted.unwrapped, nominal.unwrapped
    assert u.object_half_size == pytest.approx(0.012) and n.object_half_size == pytest.approx(0.01)
    shifted.reset(seed=2)
    assert float(u.obj.pose.p[0, 2] - n.source_center[0, 2]) == pytest.approx(0.012, abs=1e-4)  # spawned resting
    assert u.obj._bodies[0].mass == pytest.approx(0.01) and n.obj._bodies[0].mass == pytest.approx(0.02)
    mu = u.obj._bodies[0].get_collision_shapes()[0].physical_material.static_friction
    assert mu == pytest.approx(0.4)


def test_depth_noise_and_dropout_follow_the_request(pair):
    clean = pair[0]  # the module's nominal env: building another takes seconds
    noisy = make("depth_noise=4,depth_dropout=0.2")
    d0 = clean.reset(seed=4)[0]["sensor_data"]["hand_camera"]["depth"].float()
    d1 = noisy.reset(seed=4)[0]["sensor_data"]["hand_camera"]["depth"].float()
    dropped = (d1 == 0) & (d0 > 0)
    assert dropped.float().mean() == pytest.approx(0.2, abs=0.03)
    assert (d1 - d0)[~dropped].std() == pytest.approx(4.0, rel=0.15)
    again = noisy.reset(seed=4)[0]["sensor_data"]["hand_camera"]["depth"]
    assert torch.equal(again, d1.to(again.dtype))  # the same seed, the same noise
    noisy.close()


def test_latency_holds_the_previous_targets_into_the_period():
    def first_substeps(spec):
        env = make(spec, "state", render_backend="none")
        env.reset(seed=0)
        u, seen = env.unwrapped, []
        after = u._after_simulation_step
        u._after_simulation_step = lambda: (seen.append(u.agent.robot.get_qpos()[0, :6].clone()), after())[1]
        start = u.agent.robot.get_qpos()[0, :6].clone()
        env.step(torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0]))
        env.close()
        return [float((q - start).abs().max()) for q in seen]

    prompt, late = first_substeps(None), first_substeps("latency=0.03")
    assert prompt[0] > 1e-4 and max(late[:3]) < 1e-5  # held for 3 of the 5 sim steps
    assert late[4] > 1e-4


def test_a_mount_range_per_axis_draws_each_axis_in_its_own_range():
    r = Randomization.parse("camera_pos=-0.015:0.015;-0.01:0.01;-0.004:0.015,camera_rot=-6:6")
    assert r.camera_pos == (-0.015, 0.015, -0.01, 0.01, -0.004, 0.015) and r.camera_rot == (-6.0, 6.0)
    pos = r.draw("camera_pos", np.random.default_rng(0), 2000)
    assert pos.shape == (2000, 3)
    np.testing.assert_allclose(pos.min(0), [-0.015, -0.01, -0.004], atol=1e-4)
    np.testing.assert_allclose(pos.max(0), [0.015, 0.01, 0.015], atol=1e-4)


def test_ranges_follow_the_episode_seed():
    env = make("camera_fov=60:80,light=0.5:1.5", "rgbd")
    draws = []
    for seed in (0, 1, 0):
        env.reset(seed=seed)
        d = env.unwrapped.randomization_draws
        draws.append((float(d["camera_fov"][0]), float(d["light"][0])))
    env.close()
    assert draws[0] == draws[2] and draws[0] != draws[1]
    assert all(60 <= f <= 80 and 0.5 <= s <= 1.5 for f, s in draws)


NOMINAL_MIX = (
    "camera_pos=-0.012:0.012,camera_rot=-5:5,camera_fov=70:95,light=0.3:1.6,color=0.3,texture=0.7,"
    "roughness=0.1:0.9,specular=0.1:0.9,depth_model=d435,depth_noise=0:5,depth_dropout=0:0.06,latency=0:0.03"
)


def _frames(obs) -> tuple[torch.Tensor, torch.Tensor]:
    cam = obs["sensor_data"]["hand_camera"]
    return cam["rgb"], cam["depth"]


def test_a_nominal_episode_sees_the_unrandomised_scene_and_the_others_draw_as_without_it():
    """``nominal=0.5``: an episode drawn nominal after a randomised one renders, steps and reads depth bit for bit
    as the env without randomisation (camera, light, colours, textures, materials, depth model and noise, latency
    all back); an episode not drawn nominal is the one the ranges alone draw for its seed."""
    plain, mixed, ranges = make(), make(NOMINAL_MIX + ",nominal=0.5"), make(NOMINAL_MIX)
    drawn = {}
    for seed in range(8):
        mixed.reset(seed=seed)
        drawn[seed] = float(mixed.unwrapped.randomization_draws["nominal"][0])
    nominal_seeds = [s for s, v in drawn.items() if v == 1.0]
    other_seeds = [s for s, v in drawn.items() if v == 0.0]
    assert nominal_seeds and other_seeds  # seeds 0-7 draw both at 0.5
    act = torch.tensor([0.5, -0.3, 0.2, 0.4, 1.0])
    for seed in nominal_seeds[:2]:
        mixed.reset(seed=other_seeds[0])  # a randomised episode first: textures, materials and mount to undo
        om, _ = mixed.reset(seed=seed)
        op, _ = plain.reset(seed=seed)
        assert all(torch.equal(a, b) for a, b in zip(_frames(om), _frames(op)))
        for _ in range(2):
            om, *_ = mixed.step(act)
            op, *_ = plain.step(act)
            assert all(torch.equal(a, b) for a, b in zip(_frames(om), _frames(op)))
            assert torch.equal(om["agent"]["qpos"], op["agent"]["qpos"])  # latency 0: the arm moved as the plain one
    for seed in other_seeds[:2]:
        om, _ = mixed.reset(seed=seed)
        orr, _ = ranges.reset(seed=seed)
        assert all(torch.equal(a, b) for a, b in zip(_frames(om), _frames(orr)))
        assert not torch.equal(_frames(om)[0], plain.reset(seed=seed)[0]["sensor_data"]["hand_camera"]["rgb"])
    for env in (plain, mixed, ranges):
        env.close()


@pytest.mark.parametrize(
    "spec, message",
    [
        ("warp=3", "NAME one of"),
        ("light=0", "scale must be > 0"),
        ("depth_noise=-1", ">= 0"),
        ("depth_dropout=1.5", "probability"),
        ("texture=2", r"\[0, 1\]"),
        ("roughness=-0.1:0.5", r"\[0, 1\]"),
        ("object_mass=2:1", "low > high"),
        ("light=nan", "not finite"),
        ("camera_fov=abc", "not a number"),
        ("light=1;2;3", "a value or a"),
        ("light=1:2;0:1;0:1", "a value or a"),
        ("camera_pos=0:1;0;0", "per axis"),
        ("camera_pos=0:1:2", "a range is LOW:HIGH"),
        ("camera_rot=0:1;2:1;0:1", "low > high"),
        ("nominal=0.2:0.4", "one probability"),
        ("nominal=1.5", r"\[0, 1\]"),
    ],
)
def test_bad_specs_are_named(spec, message):
    with pytest.raises(ValueError, match=message):
        Randomization.parse(spec)


def test_latency_longer_than_a_period_is_refused():
    with pytest.raises(ValueError, match="shorter than the control period"):
        make("latency=0.06", "state", render_backend="none")
    with pytest.raises(ValueError, match="unknown randomisation"):
        Randomization.from_any({"lights": 1.0})


def test_build_time_ranges_are_redrawn_every_episode():
    env = make("object_size=0.8:1.25,object_mass=0.5:2", "state", render_backend="none")
    u = env.unwrapped
    sizes, masses = set(), set()
    for seed in range(4):
        env.reset(seed=seed)
        sizes.add(round(u.object_half_size, 6))
        masses.add(round(u.obj._bodies[0].mass, 6))
        assert 0.008 - 1e-9 <= u.object_half_size <= 0.0125 + 1e-9
        # the object is built at the drawn size: it rests on the tray floor at its half size
        assert float(u.obj.pose.p[0, 2] - u.source_center[0, 2]) == pytest.approx(u.object_half_size, abs=2e-4)
    assert len(sizes) == 4 and len(masses) == 4
    env.close()
    once = make("object_size=0.8:1.25", "state", render_backend="none", reconfiguration_freq=0)
    drawn = {(once.reset(seed=s), round(once.unwrapped.object_half_size, 6))[1] for s in range(3)}
    assert len(drawn) == 1  # asked for one draw per build: kept
    once.close()
