"""The reactive expert (phase read from the state) and agents.dagger: labels in the env workers, the
aggregated dataset, augmentation, a real training round on state and rgbd, resume, evaluation, bad input."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import pytest
import torch
import torch.nn.functional as F

import maniskill_irb120  # noqa: F401
from agents.common import Dataset, ExpertLabels
from agents.dagger import Args, load_policy, main, make_envs, train_round
from maniskill_irb120.action import tcp_rotation, tool_to_world
from maniskill_irb120.experts import expert_for
from maniskill_irb120.policies.nets import DeterministicActor, SpatialSoftmax, drop_rgb, jitter_rgb, random_shift

ENV = "TableClearing-IRB120-v1"


@pytest.fixture(scope="module")
def env():
    e = gym.make(ENV, obs_mode="state", render_backend="none")
    yield e
    e.close()


def rollout(env, expert, seed: int, noise: float = 0.0, switch_at: int | None = None) -> bool:
    """One episode; with ``switch_at``, a brand-new reactive expert takes over at that step."""
    gen = torch.Generator().manual_seed(seed)
    env.reset(seed=seed)
    expert.reset()
    t, done, info = 0, False, {}
    while not done:
        if switch_at is not None and t == switch_at:
            expert = expert_for(env, reactive=True)
        a = expert.act()
        a[:, :4] += noise * torch.randn(1, 4, generator=gen)
        _, _, term, trunc, info = env.step(a.clamp(-1, 1))
        done, t = bool(term[0] or trunc[0]), t + 1
    return bool(info["success"][0])


def test_reactive_phase_agrees_with_the_phase_machine(env):
    stateful, reactive = expert_for(env), expert_for(env, reactive=True)
    env.reset(seed=7)
    stateful.reset()
    same = total = 0
    done = False
    while not done:
        action = stateful.act()
        reactive.act()
        same += int(stateful.phase[0] == reactive.phase[0])
        total += 1
        _, _, term, trunc, _ = env.step(action)
        done = bool(term[0] or trunc[0])
    # they differ only where the phase machine counts steps (closing, releasing) and the state already moved on
    assert same / total >= 0.9, (same, total)


@pytest.mark.parametrize("switch_at", [15, 30, 45])
def test_a_fresh_reactive_expert_finishes_any_episode(env, switch_at):
    """Mid-approach, mid-grasp, mid-carry: it has no memory, the state alone tells it what to do."""
    assert rollout(env, expert_for(env), seed=11, switch_at=switch_at)


def test_reactive_expert_recovers_from_noisy_execution(env):
    assert all(rollout(env, expert_for(env, reactive=True), seed=s, noise=0.2) for s in (0, 1, 2))


@pytest.fixture(scope="module")
def labelled():
    """Two labelled CPU envs (env 1 in a worker process) with the auxiliary targets as well: built once for the
    label and the target tests (a worker's start is most of either)."""
    envs = make_envs(Args(num_envs=2, aux_weight=1.0), 2)
    yield envs
    envs.close()


def test_expert_labels_come_from_the_workers(env, labelled):
    _, info = labelled.reset(seed=40)
    labels = info["expert_action"]
    assert labels.shape == (2, 5)
    for i in range(2):  # worker i was seeded 40 + i: the same state in this process gives the same label
        env.reset(seed=40 + i)
        tool = expert_for(env, reactive=True).act()
        assert torch.allclose(
            labels[i], tool_to_world(tool, tcp_rotation(env.unwrapped.agent.tcp_pose.raw_pose))[0], atol=1e-5
        )
    _, _, _, _, info = labelled.step(labels)
    assert info["expert_action"].shape == (2, 5) and torch.isfinite(info["expert_action"]).all()


def test_one_batched_env_labels_the_state_an_auto_reset_starts_from():
    """The in-process (and GPU-batched) path: ManiSkill's vector env resets an ended episode within the step;
    the labels that come back are the expert's for the new episode's first state, as CPU tensors."""
    envs = make_envs(Args(num_envs=1, backend="cpu", env_kwargs=dict(max_episode_steps=3)), 1)
    try:
        o, info = envs.reset(seed=3)
        for _ in range(3):
            o, _, term, trunc, info = envs.step(info["expert_action"])
        assert bool(trunc[0]) and "final_info" in info
        base = envs.env.base_env
        expected = tool_to_world(
            expert_for(base, reactive=True).act(), tcp_rotation(base.unwrapped.agent.tcp_pose.raw_pose)
        )
        assert info["expert_action"].device.type == "cpu" and o.device.type == "cpu"
        assert torch.allclose(info["expert_action"], expected, atol=1e-5)
        assert not torch.allclose(info["final_observation"], o)  # the episode's last state is not the new start
    finally:
        envs.close()


def test_dataset_saves_only_new_rows_and_loads_back_into_the_same_slots(tmp_path):
    """Each save writes the rows added since the last one; a file the ring has overwritten is dropped; loading
    the files puts every row back in its slot, so sampling after a resume draws what it would have."""
    from agents.common import prune_row_files

    d, manifest, written = Dataset(10), None, []
    for start, n in ((0, 4), (4, 3), (7, 6), (13, 5)):  # 18 rows through a ring of 10
        d.add({"state": torch.arange(start, start + n).float().view(n, 1)}, torch.full((n, 5), float(start)))
        manifest = d.save_new_rows(tmp_path, manifest)
        prune_row_files(tmp_path, manifest)
        written.append([(f["start"], f["end"]) for f in manifest["files"]])
    assert written[:2] == [[(0, 4)], [(0, 4), (4, 7)]]
    assert written[-1] == [(7, 13), (13, 18)]  # rows 0..7 are overwritten: their files are gone from disk too
    assert sorted(p.name for p in tmp_path.glob("rows_*.pt")) == ["rows_0000000007_0000000013.pt",
                                                                   "rows_0000000013_0000000018.pt"]  # fmt: skip
    for f in manifest["files"]:  # each file holds its own rows only, never the ring's capacity
        assert torch.load(tmp_path / f["name"])["act"].shape == (f["end"] - f["start"], 5)
    e = Dataset(1)
    e.load_rows(tmp_path, manifest)
    assert (e.size, e.pos, e.added) == (d.size, d.pos, d.added) == (10, 8, 18)
    assert torch.equal(e.obs["state"], d.obs["state"]) and torch.equal(e.act, d.act)
    torch.manual_seed(0)
    a = d.sample(6, "cpu")
    torch.manual_seed(0)
    b = e.sample(6, "cpu")
    assert torch.equal(a[0]["state"], b[0]["state"]) and torch.equal(a[1], b[1])
    assert d.save_new_rows(tmp_path, manifest)["files"] == manifest["files"]  # nothing new: nothing written
    (tmp_path / manifest["files"][0]["name"]).unlink()
    with pytest.raises(FileNotFoundError, match="dataset rows .* are missing"):
        Dataset(1).load_rows(tmp_path, manifest)


def test_a_resume_restores_each_dataset_from_its_row_files_or_from_an_older_checkpoint(tmp_path):
    """DAgger keeps one dataset, SAC two (``online``, ``demos``): each comes back from the row files its
    checkpoint lists, and a checkpoint written before the row files still resumes from the rows inside it."""
    from agents.common import restore_dataset

    d = Dataset(8)
    d.add({"state": torch.arange(5).float().view(5, 1)}, torch.ones(5, 5))
    single = dict(data_rows=d.save_new_rows(tmp_path / "data", None))
    parts = dict(data_rows={"online": d.save_new_rows(tmp_path / "data" / "online", None)})
    legacy = dict(data=d.state_dict(), online=d.state_dict())
    for saved, part in ((single, None), (parts, "online"), (legacy, None), (legacy, "online")):
        e = Dataset(1)
        restore_dataset(e, saved, tmp_path / "data", part)
        assert (e.size, e.pos) == (5, 5) and torch.equal(e.obs["state"][:5], d.obs["state"][:5])
    with pytest.raises(KeyError):  # a part the checkpoint does not have is not silently an empty dataset
        restore_dataset(Dataset(1), parts, tmp_path / "data", "demos")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
def test_gpu_backend_without_cuda_is_refused_by_name():
    with pytest.raises(ValueError, match="needs CUDA"):
        make_envs(Args(num_envs=4, backend="gpu"), 4)


def test_dataset_is_a_ring_and_round_trips():
    d = Dataset(10)
    for start in (0, 7):
        d.add({"state": torch.arange(start, start + 7).float().view(7, 1)}, torch.zeros(7, 5))
    assert d.size == 10 and d.pos == 4
    assert sorted(d.obs["state"][:, 0].tolist()) == list(range(4, 14))  # the 4 oldest were dropped
    e = Dataset(1)
    e.load_state_dict(d.state_dict())
    assert e.size == 10 and e.pos == 4 and torch.equal(e.obs["state"], d.obs["state"])


def test_random_shift_moves_rgb_and_depth_together():
    torch.manual_seed(0)
    rgb = torch.zeros(3, 84, 84, 3, dtype=torch.uint8)
    depth = torch.zeros(3, 84, 84, 1, dtype=torch.int16)
    rgb[:, 40, 40] = 255
    depth[:, 40, 40] = 500
    out = random_shift({"rgb": rgb, "depth": depth, "state": torch.zeros(3, 2)}, pad=4)
    assert out["rgb"].shape == rgb.shape and out["rgb"].dtype == torch.uint8 and out["depth"].dtype == torch.int16
    for i in range(3):
        ys, xs = torch.nonzero(out["rgb"][i, :, :, 0] == 255, as_tuple=True)
        assert len(ys) == 1 and abs(int(ys[0]) - 40) <= 4 and abs(int(xs[0]) - 40) <= 4
        assert out["depth"][i, ys[0], xs[0], 0] == 500  # the same pixel in both


def test_random_shift_is_drqs_replicate_pad_and_crop():
    """The clamped-index gather gives exactly DrQ's pad-then-crop, in the images' own dtypes."""
    g = torch.Generator().manual_seed(3)
    rgb = torch.randint(0, 256, (5, 84, 84, 3), dtype=torch.uint8, generator=g)
    depth = torch.randint(0, 3000, (5, 84, 84, 1), dtype=torch.int16, generator=g)
    torch.manual_seed(7)
    out = random_shift({"rgb": rgb, "depth": depth}, pad=4)
    torch.manual_seed(7)
    dx, dy = torch.randint(0, 9, (5,)), torch.randint(0, 9, (5,))
    for name, img in (("rgb", rgb), ("depth", depth)):
        padded = F.pad(img.double().permute(0, 3, 1, 2), (4, 4, 4, 4), mode="replicate").permute(0, 2, 3, 1)
        ref = torch.stack([padded[i, dy[i] : dy[i] + 84, dx[i] : dx[i] + 84] for i in range(5)])
        assert out[name].dtype == img.dtype and torch.equal(out[name].double(), ref)
    assert (dx != 4).any() and (dy != 4).any()  # not all unshifted


def test_drop_rgb_blacks_out_whole_rgb_images_and_keeps_their_depth():
    g = torch.Generator().manual_seed(0)
    rgb = torch.randint(1, 256, (2000, 8, 8, 3), dtype=torch.uint8)
    depth = torch.randint(1, 3000, (2000, 8, 8, 1), dtype=torch.int16)
    state = torch.randn(2000, 6)
    out = drop_rgb({"rgb": rgb, "depth": depth, "state": state}, 0.3, generator=g)
    gone = (out["rgb"] == 0).flatten(1).all(1)
    kept = (out["rgb"] == rgb).flatten(1).all(1)
    assert torch.equal(gone, ~kept)  # a sample's image is blacked out whole, or left as it was
    assert 0.26 < gone.float().mean() < 0.34 and out["rgb"].dtype == torch.uint8
    assert out["depth"] is depth and out["state"] is state  # the depth (and the rest) of every sample kept
    assert torch.equal(drop_rgb({"rgb": rgb, "depth": depth}, 0.0)["rgb"], rgb)


def test_round_updates_black_out_rgb_at_the_rate_asked(monkeypatch):
    """--rgb-dropout reaches the minibatches the policy learns from, after the random shift."""
    data = Dataset(64)
    obs = {"rgb": torch.randint(1, 256, (64, 84, 84, 3), dtype=torch.uint8), "state": torch.randn(64, 6)}
    data.add({**obs, "depth": torch.randint(1, 3000, (64, 84, 84, 1), dtype=torch.int16)}, torch.rand(64, 5) * 2 - 1)
    policy = DeterministicActor((84, 84, 4), 6, 5)
    seen = []
    features = policy.features
    monkeypatch.setattr(policy, "features", lambda o: seen.append((o["rgb"] == 0).flatten(1).all(1)) or features(o))
    args = Args(obs="rgbd", updates_per_round=4, batch_size=64, rgb_dropout=0.5)
    torch.manual_seed(0)
    opt, cpu = torch.optim.AdamW(policy.parameters()), torch.device("cpu")
    train_round(policy, opt, data, args, cpu)
    dropped = torch.cat(seen).float().mean()
    assert len(seen) == 4 and 0.35 < dropped < 0.65
    seen.clear()
    train_round(policy, opt, data, replace(args, rgb_dropout=0.0), cpu)
    assert not torch.cat(seen).any()


def yiq(rgb: torch.Tensor) -> torch.Tensor:
    """(..., 3) RGB in NTSC YIQ (luma, then the chroma plane)"""
    m = torch.tensor([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]], dtype=torch.float64)
    return rgb.double() @ m.T


def test_jitter_rgb_rotates_each_samples_hue_and_scales_its_saturation_within_the_strength():
    """On one-colour images each sample's luma is scaled by its brightness alone (contrast scales about the image's
    own mean luma), its chroma rotated by at most strength x 180 deg and scaled by its saturation and its contrast
    (which blends towards the mean grey), each 1 +- strength; the draws differ per sample and follow the generator."""
    n, colour = 4000, torch.tensor([150, 100, 70], dtype=torch.uint8)
    rgb = colour.expand(n, 6, 6, 3).clone()
    depth, state = torch.randint(1, 3000, (n, 6, 6, 1), dtype=torch.int16), torch.randn(n, 6)
    out = jitter_rgb({"rgb": rgb, "depth": depth, "state": state}, 0.3, generator=torch.Generator().manual_seed(0))
    assert out["depth"] is depth and out["state"] is state and out["rgb"].dtype == torch.uint8
    assert out["rgb"].shape == rgb.shape and (out["rgb"] == out["rgb"][:, :1, :1]).all()  # still one colour each
    before, after = yiq(colour), yiq(out["rgb"][:, 0, 0])
    turn = torch.rad2deg(torch.atan2(after[:, 2], after[:, 1]) - torch.atan2(before[2], before[1]))
    turn = (turn + 180) % 360 - 180
    sat = after[:, 1:].norm(dim=1) / before[1:].norm() / (after[:, 0] / before[0])  # chroma over brightness
    assert turn.abs().max() < 54 + 3 and turn.abs().max() > 45 and turn.std() > 20  # spread over +-54 deg
    assert 0.49 - 0.02 < sat.min() < 0.6 and 1.5 < sat.max() < 1.69 + 0.03  # within (1 +- 0.3)^2
    brightness = after[:, 0] / before[0]
    assert 0.69 < brightness.min() < 0.75 and 1.25 < brightness.max() < 1.31
    again = jitter_rgb({"rgb": rgb}, 0.3, generator=torch.Generator().manual_seed(0))
    assert torch.equal(again["rgb"], out["rgb"])


def test_jitter_rgb_keeps_grey_grey_scales_contrast_about_the_mean_and_is_off_at_zero():
    g = torch.Generator().manual_seed(1)
    grey = torch.randint(60, 190, (500, 8, 8, 1), dtype=torch.uint8).expand(-1, -1, -1, 3).contiguous()
    out = jitter_rgb({"rgb": grey}, 0.2, generator=g)["rgb"].int()
    assert (out.amax(3) - out.amin(3)).max() <= 1  # no chroma to rotate or scale: grey stays grey (rounding)
    spread = out[..., 0].double().flatten(1).std(1) / grey[..., 0].double().flatten(1).std(1)
    mean = out[..., 0].double().flatten(1).mean(1) / grey[..., 0].double().flatten(1).mean(1)
    assert 0.64 - 0.03 < spread.min() and spread.max() < 1.44 + 0.03 and spread.std() > 0.1  # brightness x contrast
    assert 0.8 - 0.01 < mean.min() and mean.max() < 1.2 + 0.01  # the mean moves with the brightness alone
    obs = {"rgb": grey}
    assert jitter_rgb(obs, 0.0) is obs
    assert torch.equal(jitter_rgb(obs, 1e-7)["rgb"], grey)


def test_round_updates_jitter_the_colours_only_when_asked(monkeypatch):
    """--color-jitter reaches the minibatches the policy learns from (one-colour images, which the random shift
    leaves as they are)."""
    data = Dataset(64)
    rgb = torch.tensor([150, 100, 70], dtype=torch.uint8).expand(64, 84, 84, 3).clone()
    obs = {"rgb": rgb, "depth": torch.randint(1, 3000, (64, 84, 84, 1), dtype=torch.int16), "state": torch.randn(64, 6)}
    data.add(obs, torch.rand(64, 5) * 2 - 1)
    policy = DeterministicActor((84, 84, 4), 6, 5)
    seen = []
    features = policy.features
    monkeypatch.setattr(policy, "features", lambda o: seen.append(o["rgb"][:, 0, 0].clone()) or features(o))
    args = Args(obs="rgbd", updates_per_round=2, batch_size=64, color_jitter=0.5)
    opt, cpu = torch.optim.AdamW(policy.parameters()), torch.device("cpu")
    train_round(policy, opt, data, args, cpu)
    changed = (torch.cat(seen) != rgb[0, 0, 0]).any(1)
    assert len(seen) == 2 and changed.float().mean() > 0.9
    seen.clear()
    train_round(policy, opt, data, replace(args, color_jitter=0.0), cpu)
    assert (torch.cat(seen) == rgb[0, 0, 0]).all()


def test_round_updates_stop_at_the_budget():
    data = Dataset(64)
    data.add({"state": torch.randn(64, 6)}, torch.rand(64, 5) * 2 - 1)
    policy = DeterministicActor(None, 6, 5)
    opt = torch.optim.AdamW(policy.parameters(), lr=1e-3)
    args = Args(updates_per_round=20, batch_size=8)
    calls = []
    train_round(policy, opt, data, args, torch.device("cpu"), lambda: calls.append(1) or len(calls) > 3)
    steps = {int(v["step"]) for v in opt.state.values()}
    assert steps == {4}  # one update, then three more while in budget; the 5th check says out of time
    train_round(policy, opt, data, args, torch.device("cpu"))  # no budget: every update
    assert {int(v["step"]) for v in opt.state.values()} == {24}


def saved_dataset(checkpoint) -> Dataset:
    checkpoint = Path(checkpoint)
    data = Dataset(1)
    data.load_rows(checkpoint.parent / "data", torch.load(checkpoint, weights_only=False)["data_rows"])
    return data


SHORT = dict(max_episode_steps=50)
"""the tiny runs' episodes: 50 steps, not TableClearing's 250 (every round, evaluation and video a fifth as long;
round 0's expert episode ends before its delivery, which no test here needs)"""


@pytest.fixture
def tiny(tiny_dagger):
    """tests/agents/conftest.py's tiny DAgger run, in 50-step episodes unless a test gives its own --env-kwargs."""

    def run(runs_dir: Path, **kw) -> dict:
        return tiny_dagger(runs_dir, **{"env_kwargs": SHORT, **kw})

    return run


def test_state_run_resume_and_evaluate(tmp_path, capsys, tiny):
    res = tiny(tmp_path)
    out = capsys.readouterr().out
    last = json.loads(out.strip().splitlines()[-1])
    assert {"success_rate", "env_steps", "wall_clock_s"} <= set(last) and last["env_steps"] > 0
    # round 0 (the labelled episodes, then the first updates) says what it runs and how fast, before the bar moves
    said = [line for line in out.splitlines() if line.startswith("[dagger] round 0: ")]
    assert len(said) == 2 and "labelled episodes, then" in said[0] and " env steps in " in said[1]
    ckpt = Path(res["checkpoint"])
    saved = torch.load(ckpt, weights_only=False)
    assert "data" not in saved and saved_dataset(ckpt).size == res["dataset"] > 0
    assert (Path(res["run_dir"]) / "summary.json").is_file()
    assert list(Path(res["run_dir"]).glob("events.out.tfevents*"))
    # the budget counts the first run's wall clock too: 3 s more than it used buys one more round
    again = tiny(tmp_path, resume=ckpt, budget_min=res["wall_clock_s"] / 60 + 0.05, expert_episodes=1)
    assert again["rounds"] > res["rounds"] and again["dataset"] > res["dataset"]
    assert "[dagger] round 0" not in capsys.readouterr().out  # a resumed run has no round 0
    assert again["wall_clock_s"] > res["wall_clock_s"]
    ev = tiny(tmp_path, evaluate=True, checkpoint=ckpt, capture_video=True)
    assert ev["episodes"] == 1 and list((tmp_path / "t" / "eval" / "videos").glob("*.mp4"))
    assert json.loads((tmp_path / "t" / "eval" / "summary.json").read_text())["episodes"] == 1
    first = (tmp_path / "t" / "eval" / "summary.json").read_text()
    twice = tiny(tmp_path, evaluate=True, checkpoint=ckpt, capture_video=True)  # keeps the first one's files
    assert twice["eval_dir"] == str(tmp_path / "t" / "eval-2") and list(Path(twice["eval_dir"]).glob("videos/*.mp4"))
    assert (tmp_path / "t" / "eval" / "summary.json").read_text() == first


def test_obs_without_trains_and_evaluates_on_the_lean_state(tmp_path, tiny):
    res = tiny(tmp_path, obs_without=("agent/qvel",))
    saved = torch.load(res["checkpoint"], weights_only=False)
    data = saved_dataset(res["checkpoint"])
    assert saved["signature"]["state_dim"] == 37 and data.obs["state"].shape[1] == 37  # 45 - 8 speeds
    ev = tiny(tmp_path, evaluate=True, checkpoint=Path(res["checkpoint"]))  # the checkpoint says what it sees
    assert ev["episodes"] == 1
    # a policy exported for committing (no trainer state) evaluates as its checkpoint does, and resumes nothing
    from maniskill_irb120.policies.section import export_policy

    exported = tmp_path / "policies" / "lean.pt"
    export_policy(Path(res["checkpoint"]), exported, "python -m agents.dagger --obs-without agent/qvel")
    again = tiny(tmp_path, evaluate=True, checkpoint=exported)
    assert {k: again[k] for k in ("episodes", "successes")} == {k: ev[k] for k in ("episodes", "successes")}
    assert Path(again["eval_dir"]).parent == tmp_path / "t"  # under --runs-dir/--exp-name
    summary = json.loads((Path(again["eval_dir"]) / "summary.json").read_text())
    assert summary["checkpoint"] == str(exported) and not (tmp_path / "eval").exists()  # not beside the policy
    with pytest.raises(ValueError, match="not written by agents.dagger"):
        tiny(tmp_path, resume=exported)
    sac = tmp_path / "sac.pt"
    torch.save(dict(policy=dict(kind="sac"), command="python -m agents.sac"), sac)
    with pytest.raises(ValueError, match="an exported sac policy, not one agents.dagger trains"):
        tiny(tmp_path, evaluate=True, checkpoint=sac)


def test_rgbd_round_trains_on_camera_and_proprioception(tmp_path, tiny):
    res = tiny(tmp_path, obs="rgbd", updates_per_round=2, batch_size=8)
    saved = torch.load(res["checkpoint"], weights_only=False)
    assert saved["signature"]["image_shape"] == [84, 84, 4]
    # no privileged state: the camera policy's state vector is proprioception + TCP pose + grasp flag only
    assert saved["signature"]["state_dim"] < 40
    assert set(saved_dataset(res["checkpoint"]).obs) == {"rgb", "depth", "state"}


def test_aux_targets_are_the_object_relative_to_the_tcp_and_train_the_encoder(env, labelled, tmp_path, tiny):
    """The workers' auxiliary targets are the privileged geometry of the state just reached; a camera run with
    --aux-weight learns them alongside the actions, keeps its head across --resume, and refuses a mismatch."""
    _, info = labelled.reset(seed=50)
    for i in range(2):
        env.reset(seed=50 + i)
        u = env.unwrapped
        rel = (u.obj.pose.p - u.agent.tcp_pose.p)[0] * 10
        assert torch.allclose(info["expert_aux"][i, :3], rel, atol=1e-4)
        assert torch.allclose(info["expert_aux"][i, 3:].norm(), torch.tensor(1.0), atol=1e-5)  # sin/cos
    tool = ExpertLabels(env, frame="tool", aux=True)  # the hand camera's axes: the TCP frame
    _, info = tool.reset(seed=50)
    rel = (env.unwrapped.obj.pose.p - env.unwrapped.agent.tcp_pose.p) * 10
    assert torch.allclose(
        info["expert_aux"][:, :3],
        (tcp_rotation(env.unwrapped.agent.tcp_pose.raw_pose).transpose(1, 2) @ rel[..., None])[..., 0],
    )
    kw = dict(obs="rgbd", encoder="keypoints", updates_per_round=2, batch_size=8)
    res = tiny(tmp_path, aux_weight=1.0, initial_updates=3, **kw)
    saved = torch.load(res["checkpoint"], weights_only=False)
    data = saved_dataset(res["checkpoint"])
    assert saved["aux_head"] is not None and data.size == res["dataset"] and data.aux.shape[1:] == (5,)
    assert saved["signature"]["encoder"] == "keypoints"
    with pytest.raises(ValueError, match="aux-weight"):
        tiny(tmp_path, resume=Path(res["checkpoint"]), **kw)
    ev = tiny(tmp_path, obs="rgbd", evaluate=True, checkpoint=Path(res["checkpoint"]))  # the checkpoint's encoder
    assert ev["episodes"] == 1


MOUNT = "camera_pos=0.01;-0.008;0.004,camera_rot=3;-2;5"


def test_aux_mount_targets_are_the_drawn_mount_and_a_run_keeps_them_across_resume(env, tmp_path, tiny):
    """--aux-mount appends the camera's drawn offset from its nominal mount (cm, units of 5 deg) to the targets:
    zero on an env that draws no mount, the drawn value on one that does; a camera run trains an 11-target head,
    and a resume that disagrees on --aux-mount is refused by name."""
    plain = ExpertLabels(env, frame="tool", aux=True, aux_mount=True)
    _, info = plain.reset(seed=50)
    assert info["expert_aux"].shape == (1, 11) and not info["expert_aux"][:, 5:].any()
    assert torch.equal(
        info["expert_aux"][:, :5], ExpertLabels(env, frame="tool", aux=True).reset(seed=50)[1]["expert_aux"]
    )
    shifted = gym.make(ENV, obs_mode="rgbd", randomization=MOUNT)
    try:
        _, info = ExpertLabels(shifted, frame="tool", aux=True, aux_mount=True).reset(seed=50)
        want = torch.tensor([[1.0, -0.8, 0.4, 0.6, -0.4, 1.0]])
        assert torch.allclose(info["expert_aux"][:, 5:], want, atol=1e-5)
    finally:
        shifted.close()
    with pytest.raises(ValueError, match="--aux-mount needs --aux-weight"):
        ExpertLabels(env, aux_mount=True)
    kw = dict(obs="rgbd", encoder="keypoints", updates_per_round=2, batch_size=8, aux_weight=1.0)
    res = tiny(tmp_path, aux_mount=True, initial_updates=3, env_kwargs=dict(randomization=MOUNT), **kw)
    saved = torch.load(res["checkpoint"], weights_only=False)
    data = saved_dataset(res["checkpoint"])
    assert data.aux.shape[1:] == (11,) and saved["aux_head"]["2.bias"].shape == (11,)
    assert torch.allclose(data.aux[: data.size, 5:], torch.tensor([1.0, -0.8, 0.4, 0.6, -0.4, 1.0]), atol=1e-5)
    with pytest.raises(ValueError, match="disagree on --aux-mount"):
        tiny(tmp_path, resume=Path(res["checkpoint"]), env_kwargs=dict(randomization=MOUNT), **kw)


def test_aux_loss_fits_a_target_the_actions_do_not_need():
    torch.manual_seed(0)
    data = Dataset(256)
    x = torch.randn(256, 6)
    data.add({"state": x}, torch.zeros(256, 5), aux=x[:, :5] * 2)
    policy = DeterministicActor(None, 6, 5)
    head = torch.nn.Sequential(torch.nn.Linear(policy.encoder.out_dim, 5))
    opt = torch.optim.AdamW([*policy.parameters(), *head.parameters()], lr=1e-3)
    args = Args(batch_size=64, aux_weight=1.0)
    first = train_round(policy, opt, data, args, torch.device("cpu"), aux_head=head, updates=1)
    last = train_round(policy, opt, data, args, torch.device("cpu"), aux_head=head, updates=300)
    assert last["aux"] < 0.1 * first["aux"] and {"bc", "aux"} == set(last)
    with pytest.raises(ValueError, match="auxiliary"):
        data.add({"state": x[:1]}, torch.zeros(1, 5))  # a row without its target


def test_spatial_softmax_finds_a_bright_pixel():
    maps = torch.full((2, 1, 21, 21), -10.0)
    maps[0, 0, 0, 20] = maps[1, 0, 10, 5] = 10.0  # top right; the middle row, a quarter from the left
    xy = SpatialSoftmax(21, 21)(maps)
    assert torch.allclose(xy, torch.tensor([[1.0, -1.0], [-0.5, 0.0]]), atol=1e-3)


def test_keypoint_encoder_needs_a_camera_and_names_itself():
    with pytest.raises(ValueError, match="unknown encoder"):
        DeterministicActor((84, 84, 4), 6, 5, encoder="resnet")
    with pytest.raises(ValueError, match="camera"):
        DeterministicActor(None, 6, 5, encoder="keypoints")
    assert "encoder" not in DeterministicActor((84, 84, 4), 6, 5).signature()  # older checkpoints still match
    for bad, match in (
        (dict(encoder="keypoints"), "--obs state has no image"),
        (dict(aux_weight=float("nan")), "--aux-weight"),
        (dict(aux_weight=-1.0), "--aux-weight"),
        (dict(aux_mount=True), "--aux-mount .* needs --aux-weight"),
        (dict(obs="rgbd", rgb_dropout=1.0), "--rgb-dropout is a probability"),
        (dict(obs="rgbd", rgb_dropout=float("nan")), "--rgb-dropout is a probability"),
        (dict(rgb_dropout=0.3), "--rgb-dropout .* --obs state has none"),
        (dict(obs="rgbd", color_jitter=1.5), "--color-jitter is a strength in"),
        (dict(obs="rgbd", color_jitter=float("nan")), "--color-jitter is a strength in"),
        (dict(color_jitter=0.3), "--color-jitter .* --obs state has none"),
        (dict(initial_updates=-5), "--initial-updates"),
    ):
        with pytest.raises(ValueError, match=match):
            main(Args(**bad))  # refused before any env starts


def test_widening_keeps_the_narrow_actors_actions_and_its_new_columns_learn():
    torch.manual_seed(0)
    narrow = DeterministicActor((84, 84, 4), 6, 5, encoder="keypoints")
    wide = DeterministicActor((84, 84, 4), 6, 5, encoder="keypoints-depth")
    depth_before = {k: v.clone() for k, v in wide.state_dict().items() if ".depth_" in k}
    wide.widen(narrow.state_dict())
    obs = dict(
        rgb=torch.randint(0, 256, (4, 84, 84, 3), dtype=torch.uint8),
        depth=torch.randint(0, 2000, (4, 84, 84, 1), dtype=torch.int16),
        state=torch.randn(4, 6),
    )
    assert torch.allclose(narrow(obs), wide(obs), atol=1e-6)
    after = wide.state_dict()
    assert all(torch.equal(after[k], v) for k, v in depth_before.items())  # the depth stack keeps its fresh weights
    begin, end = wide.encoder.image_dim, wide.encoder.image_dim + wide.encoder.depth_dim
    assert (begin, end) == (64, 96) and not after["head.0.weight"][:, begin:end].any()
    # the depth image alone reaches the new keypoints: an RGB change moves the RGB-D stack's, not these
    feats = wide.features(obs)[:, begin:end]
    assert torch.equal(wide.features(dict(obs, rgb=255 - obs["rgb"]))[:, begin:end], feats)
    assert not torch.equal(wide.features(dict(obs, depth=obs["depth"].flip(1)))[:, begin:end], feats)
    wide(obs).square().sum().backward()
    assert wide.head[0].weight.grad[:, begin:end].abs().sum() > 0  # the zero columns grow from their gradient
    with pytest.raises(ValueError, match="only a 'keypoints-depth' actor widens"):
        narrow.widen(narrow.state_dict())
    with pytest.raises(ValueError, match="not a 'keypoints' actor's"):
        wide.widen(DeterministicActor((84, 84, 4), 7, 5, encoder="keypoints").state_dict())
    with pytest.raises(ValueError, match="not a 'keypoints' actor's"):
        wide.widen(DeterministicActor((84, 84, 4), 6, 5).state_dict())  # the Nature CNN's


def test_bad_checkpoints_are_named(tmp_path):
    with pytest.raises(ValueError, match="--checkpoint"):
        main(Args(evaluate=True))
    wrong = tmp_path / "ppo.pt"
    torch.save(dict(format="maniskill_irb120.ppo/1"), wrong)
    with pytest.raises(ValueError, match="not written by agents.dagger"):
        main(Args(evaluate=True, checkpoint=wrong))
    with pytest.raises(FileNotFoundError):
        main(Args(resume=tmp_path / "missing.pt"))


def test_updates_take_every_core_and_collection_one_thread_beside_the_workers(tmp_path, monkeypatch, tiny):
    """With CPU workers the learner's per-step ops run on one thread (more only spin against the workers) and a
    round of updates, which the workers sit out, on the process's own threads (before: one, hidden, for both)."""
    from agents import dagger

    seen: dict[str, list[int]] = {"collect": [], "update": []}
    collect, train_round = dagger.collect, dagger.train_round

    def counting_collect(*a, **k):
        seen["collect"].append(torch.get_num_threads())
        return collect(*a, **k)

    def counting_round(*a, **k):
        seen["update"].append(torch.get_num_threads())
        return train_round(*a, **k)

    monkeypatch.setattr(dagger, "collect", counting_collect)
    monkeypatch.setattr(dagger, "train_round", counting_round)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        tiny(tmp_path, num_envs=2, backend="cpu")
    finally:
        torch.set_num_threads(before)
    assert seen["collect"] and set(seen["collect"]) == {1}
    assert seen["update"] and set(seen["update"]) == {2}


def test_env_kwargs_from_the_command_line_reach_the_env_as_numbers_where_they_are_numbers():
    import tyro

    args = tyro.cli(
        Args,
        args=["--env-kwargs", "reconfiguration_freq", "2", "randomization", "object_mass=0.5:2,light=0.5"],
    )
    assert args.env_kwargs == {"reconfiguration_freq": 2, "randomization": "object_mass=0.5:2,light=0.5"}
    env = gym.make("GraspLift-IRB120-v1", obs_mode="state", **args.env_kwargs)
    masses = []
    for seed in range(6):  # ManiSkill counts resets modulo reconfiguration_freq: a string "2" raised here
        env.reset(seed=seed)
        masses.append(float(env.unwrapped.randomization_draws["object_mass"][0]))
    env.close()
    # a new draw per scene build, i.e. every second episode (not every one, not never)
    assert len(set(masses)) in (3, 4) and sum(a == b for a, b in zip(masses, masses[1:])) >= 2, masses


def test_init_policy_starts_from_another_runs_weights_and_refuses_a_different_policy(tmp_path, tiny):
    round0 = dict(budget_min=None, total_env_steps=1)  # round 0 alone: the expert's episode and its 5 updates
    a = tiny(tmp_path, exp_name="a", **round0)
    frozen = dict(learning_rate=0.0, weight_decay=0.0, **round0)  # the updates leave the weights where they started
    # another seed: round 0's episodes differ from a's, and would give a state normalisation of their own
    b = tiny(tmp_path, exp_name="b", init_policy=Path(a["checkpoint"]), seed=2, **frozen)
    c = tiny(tmp_path, exp_name="c", seed=2, **frozen)
    wa, wb, wc = (torch.load(r["checkpoint"], weights_only=False)["model"] for r in (a, b, c))
    params = [k for k, v in wa.items() if v.is_floating_point()]
    assert all(torch.equal(wa[k], wb[k]) for k in params)  # the normalisation's mean and std among them
    assert not torch.equal(wa["norm.mean"], wc["norm.mean"])  # which another seed's episodes would have moved
    assert not all(torch.equal(wa[k], wc[k]) for k in params)  # without it: a fresh policy
    with pytest.raises(ValueError, match=r"action_frame='world' \(this run: 'tool'\)"):
        tiny(tmp_path, exp_name="d", init_policy=Path(a["checkpoint"]), action_frame="tool")
    with pytest.raises(ValueError, match="pick one"):
        tiny(tmp_path, exp_name="e", init_policy=Path(a["checkpoint"]), resume=Path(a["checkpoint"]))
    # a run started from --init-policy resumes with it among its own arguments (as the command line's --resume alone
    # gives them): it goes on from its own weights and dataset; another --init-policy with --resume is refused
    resumed = tiny(tmp_path, exp_name="b", init_policy=Path(a["checkpoint"]), resume=Path(b["checkpoint"]),
                   budget_min=None, total_env_steps=b["env_steps"] + 1, expert_episodes=1)  # fmt: skip
    assert resumed["rounds"] > b["rounds"] and resumed["dataset"] > b["dataset"]
    with pytest.raises(ValueError, match="pick one"):
        tiny(tmp_path, exp_name="b", init_policy=Path(c["checkpoint"]), resume=Path(b["checkpoint"]))


def test_init_data_starts_the_dataset_with_another_runs_rows_and_refuses_rows_of_another_kind(tmp_path, tiny):
    round0 = dict(budget_min=None, total_env_steps=1)
    a = tiny(tmp_path, exp_name="a", **round0)
    b = tiny(tmp_path, exp_name="b", init_data=Path(a["checkpoint"]), seed=2, **round0)
    assert b["env_steps"] == a["env_steps"] and b["dataset"] == a["dataset"] + b["env_steps"]  # its own steps only
    rows_a, rows_b = saved_dataset(a["checkpoint"]), saved_dataset(b["checkpoint"])
    assert torch.equal(rows_b.obs["state"][: a["dataset"]], rows_a.obs["state"][: a["dataset"]])
    assert torch.equal(rows_b.act[: a["dataset"]], rows_a.act[: a["dataset"]])
    assert not torch.equal(rows_b.obs["state"][a["dataset"] :], rows_a.obs["state"])  # then its own episodes
    # the resumed run goes on from its own dataset, which holds a's rows already
    resumed = tiny(tmp_path, exp_name="b", init_data=Path(a["checkpoint"]), resume=Path(b["checkpoint"]),
                   budget_min=None, total_env_steps=b["env_steps"] + 1, expert_episodes=1)  # fmt: skip
    assert resumed["dataset"] > b["dataset"]
    for bad, match in (
        (dict(action_frame="tool"), r"rows of another kind: action_frame='world' \(this run: 'tool'\)"),
        (dict(aux_weight=1.0), "rows of another kind: aux targets off"),
        (dict(resume=Path(b["checkpoint"]), init_data=Path(b["checkpoint"])), "--init-data .* pick one"),
    ):
        with pytest.raises(ValueError, match=match):
            tiny(tmp_path, exp_name="d", **{"init_data": Path(a["checkpoint"]), **round0, **bad})
    with pytest.raises(FileNotFoundError, match="--init-data .*no such checkpoint"):
        tiny(tmp_path, exp_name="d", init_data=tmp_path / "none.pt", **round0)
    assert not (tmp_path / "d").exists()  # each refused before its run began


def test_init_policy_widens_a_keypoints_policy_into_keypoints_depth_acting_as_it_did(tmp_path, tiny):
    camera = dict(obs="rgbd", action_frame="tool", batch_size=8, updates_per_round=2, budget_min=None,
                  total_env_steps=1)  # fmt: skip
    a = tiny(tmp_path, exp_name="a", encoder="keypoints", **camera)
    frozen = dict(camera, learning_rate=0.0, weight_decay=0.0)
    b = tiny(tmp_path, exp_name="b", encoder="keypoints-depth", init_policy=Path(a["checkpoint"]), **frozen)
    (pa, _), (pb, _) = (load_policy(Path(r["checkpoint"]), "cpu") for r in (a, b))
    assert pb.signature()["encoder"] == "keypoints-depth" and pb.encoder.depth_cnn is not None
    g = torch.Generator().manual_seed(0)
    obs = dict(
        rgb=torch.randint(0, 256, (6, 84, 84, 3), dtype=torch.uint8, generator=g),
        depth=torch.randint(0, 2000, (6, 84, 84, 1), dtype=torch.int16, generator=g),
        state=torch.randn(6, pa.state_dim, generator=g),
    )
    assert (pa(obs) - pb(obs)).abs().max() < 1e-5, (pa(obs) - pb(obs)).abs().max()
    with pytest.raises(ValueError, match="is not this run's policy: signature="):  # no narrowing the other way
        tiny(tmp_path, exp_name="c", encoder="keypoints", init_policy=Path(b["checkpoint"]), **camera)


def test_student_selection_keeps_the_best_validated_round_and_the_held_out_evaluation_scores_it(
    tmp_path, tiny, monkeypatch
):
    """--select-episodes: every --select-freq rounds the policy plays the validation seeds (not the held-out ones);
    best.pt changes only on a better score (success, then return), the held-out episodes score it, --evaluate reads
    it, and --resume refuses it (no dataset, no optimiser: a policy, not a run)."""
    import agents.dagger as dagger
    from agents.common import EVAL_SEED, VALIDATION_SEED

    scores = [(0.2, 5.0), (0.6, 9.0), (0.6, 8.0), (0.1, 2.0)]
    validations, held_out = [], []
    real = dagger.final_evaluation

    def scripted(policy, args, device, video_dir, first_seed=EVAL_SEED):
        weights = [p.detach().clone() for p in policy.parameters()]
        if first_seed == EVAL_SEED:
            held_out.append(weights)
            return dict(success_rate=0.0)
        validations.append((first_seed, args.eval_episodes, weights))
        s, r = scores[len(validations) - 1] if len(validations) <= len(scores) else (0.0, 0.0)
        return {"success_rate": s, "return": r}

    monkeypatch.setattr(dagger, "final_evaluation", scripted)
    # an env-step budget, so that a loaded machine runs as many rounds as a quiet one: round 0 (one expert episode)
    # and round 1 (one learner episode) take at most 2 x 50 steps (SHORT), so a 101-step budget starts round 2 at least
    res = tiny(tmp_path, budget_min=None, total_env_steps=101, select_episodes=3, select_freq=1)
    assert res["rounds"] >= 3 and len(validations) == res["rounds"]  # one a round; none again at the budget's end
    assert {(seed, n) for seed, n, _ in validations} == {(VALIDATION_SEED, 3)}
    assert res["selected"] == dict(round=2, env_steps=res["selected"]["env_steps"], validation_success_rate=0.6,
                                   validation_episodes=3)  # fmt: skip
    ckpts = tmp_path / "t" / "checkpoints"
    assert res["checkpoint"] == str(ckpts / "best.pt") and res["last_checkpoint"] == str(ckpts / "latest.pt")
    best = torch.load(ckpts / "best.pt", weights_only=False)
    assert best["counters"]["best"]["round"] == 2 and "optimizer" not in best and "data_rows" not in best
    second = validations[1][2]
    assert all(torch.equal(a, b) for a, b in zip(held_out[0], second))  # the held-out episodes scored round 2
    last = torch.load(ckpts / "latest.pt", weights_only=False)["model"]
    assert any(not torch.equal(a, b) for a, b in zip(last.values(), best["model"].values()))  # training went on

    monkeypatch.setattr(dagger, "final_evaluation", real)
    assert tiny(tmp_path, evaluate=True, checkpoint=ckpts / "best.pt")["episodes"] == 1
    with pytest.raises(ValueError, match="holds a selected policy .*latest.pt"):
        tiny(tmp_path, resume=ckpts / "best.pt")
    with pytest.raises(ValueError, match="--select-freq"):
        tiny(tmp_path, select_episodes=2, select_freq=0)


def test_no_round_starts_that_would_end_after_the_budget(tmp_path, tiny, monkeypatch):
    """A student's rounds keep to its stage's minutes: a round and the validation after it start only where the
    longest of each so far still end within the budget (round 0, the initial fit, estimates nothing). The clock
    jumps 100 s at each validation, so the stop is the budget's arithmetic and not this machine's speed."""
    import agents.dagger as dagger
    from agents.common import EVAL_SEED

    jumped = [0.0]

    class JumpingClock(dagger.Clock):
        def __call__(self) -> float:
            return super().__call__() + jumped[0]

    def scripted(policy, args, device, video_dir, first_seed=EVAL_SEED):
        if first_seed != EVAL_SEED:
            jumped[0] += 100.0
        return {"success_rate": 0.5, "return": 1.0}

    monkeypatch.setattr(dagger, "Clock", JumpingClock)
    monkeypatch.setattr(dagger, "final_evaluation", scripted)
    res = tiny(tmp_path, budget_min=250 / 60, select_episodes=1, select_freq=1)
    assert res["rounds"] == 2 and 200.0 < res["wall_clock_s"] <= 250.0


def test_a_student_stopped_by_its_budget_validates_its_last_round_once(tmp_path, tiny, monkeypatch):
    """Selection rounds that never come before the budget ends: the last weights are validated once, at the end."""
    import agents.dagger as dagger
    from agents.common import EVAL_SEED

    validations = []

    def scripted(policy, args, device, video_dir, first_seed=EVAL_SEED):
        if first_seed != EVAL_SEED:
            validations.append(first_seed)
        return {"success_rate": 0.5, "return": 1.0}

    monkeypatch.setattr(dagger, "final_evaluation", scripted)
    res = tiny(tmp_path, select_episodes=2, select_freq=1000)
    assert len(validations) == 1 and res["selected"]["round"] == res["rounds"]


def test_an_env_step_budget_ends_the_rounds_and_spans_a_resume(tmp_path, tiny):
    """--total-env-steps alone (no wall guard): round 0 always runs, and a round starts only while the run, counting
    its env steps before a --resume, is below the budget."""
    first = tiny(tmp_path, budget_min=None, total_env_steps=1)  # the expert's round passes it
    assert first["rounds"] == 1 and first["env_steps"] >= 1 and first["stopped_early"] is False
    assert first["total_env_steps"] == 1 and first["max_minutes"] is None
    again = tiny(tmp_path, budget_min=None, total_env_steps=1, resume=Path(first["checkpoint"]))
    assert again["rounds"] == 1 and again["env_steps"] == first["env_steps"]  # nothing left of the budget
    more = tiny(tmp_path, budget_min=None, total_env_steps=first["env_steps"] + 1, resume=Path(first["checkpoint"]))
    assert more["rounds"] == 2 and more["env_steps"] > first["env_steps"]
