"""The GPU acceptance checks: what the first run on a GPU has to show before anyone trains there.

Each check drives a task the way training does and returns a verdict (:class:`CheckResult`) with a one-line
reason, so that a GPU path that breaks says so here instead of deep in a training run (which GPU runs the
project has had: ``docs/gpu.md``). Every check takes the sim backend and the batch size: ``tests/gpu/`` runs them on
``physx_cuda`` with 512 envs, ``maniskill-irb120 doctor --gpu`` runs them for its report, and the default test
suite runs the same functions on ``physx_cpu`` (one env, ManiSkill's limit there) so that the check code itself
is known to work before a GPU ever runs it. The verdicts are separate pure functions (``*_verdict``), tested on
hand-made batches that hold the bugs each check exists to catch.

This module imports without CUDA; the checks by name, the timing and the fresh-process runs are in
``acceptance_runs.py``; the trainers' and the benchmark's runs are a source checkout's
(``benchmarks/gpu_acceptance.py``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import gymnasium as gym
import torch

import maniskill_irb120  # noqa: F401  (registers the tasks)
from maniskill_irb120.envs.grasp_lift import ENV_ID as GRASP_LIFT
from maniskill_irb120.envs.stack_cube import ENV_ID as STACK_CUBE
from maniskill_irb120.envs.table_clearing import ENV_ID as TABLE_CLEARING

ENV_IDS = (TABLE_CLEARING, GRASP_LIFT, STACK_CUBE)
OBS_MODES = ("state", "state_dict", "none", "rgbd", "rgb", "depth", "pointcloud", "sensor_data")
"""the obs modes docs/tasks.md promises (every ManiSkill mode we name, plus rgbd); combinations are not swept"""
STATE_ONLY = ("state", "state_dict", "none")
CAMERA = "hand_camera"
IMAGE_HW = (84, 84)
COLLISION_SEEDS = (0, 6)
"""episode seeds of the scripted collision (the CPU contact test's seeds)"""
DOWN = (1.0, 0.0, 0.0, 0.0, 1.0)
"""pd_ee_delta_tool: straight down along the approach axis, gripper open — into the tray or table"""


@dataclass
class CheckResult:
    name: str
    ok: bool | None
    """True: PASS, False: FAIL, None: SKIP (the reason says why)"""
    reason: str
    seconds: float = 0.0

    @property
    def status(self) -> str:
        return "SKIP" if self.ok is None else ("PASS" if self.ok else "FAIL")

    def to_dict(self) -> dict:
        return dict(asdict(self), status=self.status)


def timed_check(name: str, fn: Callable[..., tuple[bool | None, str]], /, **kwargs) -> CheckResult:
    """Run one check; an exception is that check's FAIL (with its message), never the end of the report."""
    t0 = time.perf_counter()
    try:
        ok, reason = fn(**kwargs)
    except Exception as e:  # noqa: BLE001 - any failure is this check's verdict
        ok, reason = False, f"{type(e).__name__}: {str(e).strip().splitlines()[0][:300] if str(e).strip() else ''}"
    return CheckResult(name, ok, reason, round(time.perf_counter() - t0, 2))


def make(env_id: str, num_envs: int, sim_backend: str, obs_mode: str = "state", **kwargs) -> gym.Env:
    """A task as the acceptance runs need it: no renderer where the obs mode needs no camera."""
    if obs_mode in STATE_ONLY:
        kwargs.setdefault("render_backend", "none")
    return gym.make(env_id, num_envs=num_envs, sim_backend=sim_backend, obs_mode=obs_mode, **kwargs)


def expected_device(sim_backend: str) -> str:
    return "cuda" if "cuda" in sim_backend or sim_backend == "gpu" else "cpu"


def random_actions(env: gym.Env, seed: int) -> Callable[[], torch.Tensor]:
    u = env.unwrapped
    gen = torch.Generator(device=u.device).manual_seed(seed)
    shape = (u.num_envs, *u.single_action_space.shape)
    return lambda: torch.rand(shape, generator=gen, device=u.device) * 2 - 1


def reset_indices(num_envs: int) -> torch.Tensor:
    """Every other env (env 0 alone with one env): reset envs and running envs side by side."""
    return torch.arange(0, num_envs, 2) if num_envs > 1 else torch.zeros(1, dtype=torch.long)


# --------------------------------------------------------------------------- observations
def obs_problems(obs: Any, space: gym.Space, num_envs: int, device: str, where: str = "obs") -> list[str]:
    """What is wrong with one batched observation against its single-env space: every leaf a tensor of shape
    (num_envs, *space shape) on ``device``, floating leaves finite."""
    if isinstance(space, gym.spaces.Dict):
        if not isinstance(obs, dict):
            return [f"{where}: a {type(obs).__name__}, expected a dict"]
        missing = sorted(set(space.spaces) - set(obs))
        out = [f"{where}: missing {missing}"] if missing else []
        for k in space.spaces:
            if k in obs:
                out += obs_problems(obs[k], space[k], num_envs, device, f"{where}/{k}")
        return out
    if not isinstance(obs, torch.Tensor):
        return [f"{where}: a {type(obs).__name__}, expected a torch tensor"]
    out = []
    if tuple(obs.shape) != (num_envs, *space.shape):
        out.append(f"{where}: shape {tuple(obs.shape)}, expected {(num_envs, *space.shape)}")
    if obs.device.type != device:
        out.append(f"{where}: on {obs.device}, expected {device}")
    if obs.dtype.is_floating_point and not bool(torch.isfinite(obs).all()):
        out.append(f"{where}: {int((~torch.isfinite(obs)).sum())} values not finite")
    return out


def check_obs_modes(
    sim_backend: str,
    num_envs: int,
    env_ids: Sequence[str] = ENV_IDS,
    obs_modes: Sequence[str] = OBS_MODES,
    steps: int = 2,
) -> tuple[bool, str]:
    """Every task in every obs mode resets and steps with batched, finite observations on the right device."""
    device = expected_device(sim_backend)
    problems: list[str] = []
    for env_id in env_ids:
        for mode in obs_modes:
            env = make(env_id, num_envs, sim_backend, mode)
            try:
                u = env.unwrapped
                obs, _ = env.reset(seed=0)
                found = obs_problems(obs, u.single_observation_space, num_envs, device)
                act = random_actions(env, 0)
                for _ in range(steps):
                    obs, rew, term, trunc, _ = env.step(act())
                    found += obs_problems(obs, u.single_observation_space, num_envs, device)
                    for name, x in (("reward", rew), ("terminated", term), ("truncated", trunc)):
                        if tuple(x.shape) != (num_envs,) or (x.dtype.is_floating_point and not torch.isfinite(x).all()):
                            found.append(f"{name}: shape {tuple(x.shape)} or not finite")
                problems += [f"{env_id} {mode}: {p}" for p in found]
            finally:
                env.close()
    if problems:
        return False, f"{len(problems)} problems, first: {problems[0]}"
    return True, f"{len(env_ids)} tasks x {len(obs_modes)} obs modes, num_envs={num_envs}, {steps} steps each"


# --------------------------------------------------------------------------- partial resets
def partial_reset_verdict(
    idx: torch.Tensor, start: dict, before: dict, after: dict, rest_qpos: torch.Tensor, atol: float = 1e-5
) -> tuple[bool, str]:
    """``start``: right after the first reset; ``before``/``after``: around ``reset(options={"env_idx": idx})``.
    Each a dict of (N, ...) tensors: ``state`` (the env's flat state), ``obj`` (target object's raw pose),
    ``qpos``. The reset envs must start afresh (object moved from their first start, robot at rest, and, with
    several, each its own start); the others must not change at all."""
    n = before["state"].shape[0]
    reset = torch.zeros(n, dtype=torch.bool)
    reset[idx.cpu()] = True
    keep = ~reset
    if keep.any():
        moved = (after["state"][keep] - before["state"][keep]).abs().amax(1)
        if bool((moved > atol).any()):
            bad = torch.arange(n)[keep][moved > atol].tolist()
            return False, f"envs not reset changed state: {bad[:8]} (max change {float(moved.max()):.2e})"
    same_start = (after["obj"][reset, :2] - start["obj"][reset, :2]).norm(dim=1) < 1e-4
    if bool(same_start.any()):
        return False, f"reset envs {torch.arange(n)[reset][same_start].tolist()[:8]} got their first start again"
    off_rest = (after["qpos"][reset] - rest_qpos.to(after["qpos"])).abs().amax(1)
    if bool((off_rest > 1e-3).any()):
        return False, f"reset envs' robots not at the rest pose (max {float(off_rest.max()):.3g} rad)"
    xy = after["obj"][reset, :2]
    if len(xy) > 1:
        d = torch.cdist(xy, xy) + torch.eye(len(xy)) * 1e9
        if float(d.min()) < 1e-6:
            return False, "two reset envs got the same object start (a start shared across envs)"
    return (
        True,
        f"{int(reset.sum())} of {n} envs reset to fresh, distinct starts; the other {int(keep.sum())} unchanged",
    )


def _snapshot(u) -> dict:
    return dict(
        state=u.get_state().detach().cpu().clone(),
        obj=u.target_object.pose.raw_pose.detach().cpu().clone(),
        qpos=u.agent.robot.get_qpos().detach().cpu().clone(),
    )


def check_partial_resets(sim_backend: str, num_envs: int, env_ids: Sequence[str] = ENV_IDS) -> tuple[bool, str]:
    """Partial resets (``options={"env_idx": ...}``) give fresh per-env starts and leave running envs alone."""
    reasons = []
    for env_id in env_ids:
        env = make(env_id, num_envs, sim_backend)
        try:
            u = env.unwrapped
            env.reset(seed=0)
            start = _snapshot(u)
            act = random_actions(env, 1)
            for _ in range(3):
                env.step(act())
            before = _snapshot(u)
            idx = reset_indices(num_envs)
            env.reset(options=dict(env_idx=idx.to(u.device)))
            rest = torch.as_tensor(u.agent.keyframes["rest"].qpos, dtype=torch.float32)
            ok, why = partial_reset_verdict(idx, start, before, _snapshot(u), rest)
        finally:
            env.close()
        if not ok:
            return False, f"{env_id}: {why}"
        reasons.append(why)
    return True, f"{len(env_ids)} tasks: {reasons[0]}"


# --------------------------------------------------------------------------- controller targets
def controller_reset_verdict(
    idx: torch.Tensor, before: dict, after: dict, measured: dict, atol: float = 1e-4
) -> tuple[bool, str]:
    """Each dict: target name -> (N, k). Reset envs' targets must equal the measured robot (their new start);
    the other envs' targets must be untouched, and must differ from the measured robot (else a reset of every
    env would pass unseen)."""
    n = next(iter(before.values())).shape[0]
    reset = torch.zeros(n, dtype=torch.bool)
    reset[idx.cpu()] = True
    keep = ~reset
    ahead = torch.zeros(n, dtype=torch.bool)
    for k in before:
        err = (after[k][reset] - measured[k][reset]).abs().amax(1)
        if bool((err > atol).any()):
            return False, f"{k}: reset envs' targets are {float(err.max()):.2e} from their new start"
        if keep.any():
            changed = (after[k][keep] - before[k][keep]).abs().amax(1)
            if bool((changed > 1e-6).any()):
                bad = torch.arange(n)[keep][changed > 1e-6].tolist()
                return False, f"{k}: targets of envs not reset were reset too: {bad[:8]}"
            ahead[keep] |= (before[k][keep] - measured[k][keep]).abs().amax(1) > 10 * atol
    if keep.any() and not bool(ahead[keep].all()):
        return False, "the scripted targets were not ahead of the robot: the check could not tell a full reset"
    return True, f"{int(reset.sum())} reset envs' targets at their new start; {int(keep.sum())} others' kept"


def _targets(u) -> tuple[dict, dict]:
    """(targets, what each target should equal after a reset) of every controller, as (N, k) CPU tensors."""
    targets, measured = {}, {}
    for uid, c in u.agent.controller.controllers.items():
        targets[f"{uid}.target_qpos"] = c._target_qpos.detach().cpu().clone()
        measured[f"{uid}.target_qpos"] = c.qpos.detach().cpu().clone()
        if getattr(c, "_target_pose", None) is not None:
            targets[f"{uid}.target_pose"] = c._target_pose.detach().cpu().reshape(u.num_envs, -1).clone()
            tcp = u.agent.robot.pose.inv() * u.agent.tcp_pose
            measured[f"{uid}.target_pose"] = tcp.to_transformation_matrix().detach().cpu().reshape(u.num_envs, -1)
    return targets, measured


def check_controller_reset(sim_backend: str, num_envs: int, env_id: str = TABLE_CLEARING) -> tuple[bool, str]:
    """With accumulated targets (``pd_ee_target_delta_tool``), a partial reset resets the targets of only the
    envs it resets, to their new start."""
    env = make(env_id, num_envs, sim_backend, control_mode="pd_ee_target_delta_tool")
    try:
        u = env.unwrapped
        env.reset(seed=0)
        a = torch.tensor([[0.5, 0.5, -0.5, 0.5, 1.0]], device=u.device).repeat(num_envs, 1)
        for _ in range(3):
            env.step(a)
        u.agent.set_action(-a)  # targets a step ahead of the robot (no physics step yet)
        before, _ = _targets(u)
        idx = reset_indices(num_envs)
        env.reset(options=dict(env_idx=idx.to(u.device)))
        after, measured = _targets(u)
        return controller_reset_verdict(idx, before, after, measured)
    finally:
        env.close()


# --------------------------------------------------------------------------- contacts
def first_collisions(sim_backend: str, num_envs: int, seeds: Sequence[int], env_id: str, steps: int) -> list[int]:
    """Per env (seeds tiled over the batch; with one env, one episode per seed): the first step whose
    ``info["collided"]`` is set driving straight down, -1 if none. On the CPU the contact scan that sets it is
    compared with the per-pair queries (the GPU's layout) at every step."""
    runs = [[s] for s in seeds] if num_envs == 1 else [[seeds[i % len(seeds)] for i in range(num_envs)]]
    out: list[int] = []
    for seed_list in runs:
        env = make(env_id, num_envs, sim_backend, control_mode="pd_ee_delta_tool")
        try:
            u = env.unwrapped
            env.reset(seed=seed_list if num_envs > 1 else seed_list[0])
            first = torch.full((num_envs,), -1, dtype=torch.long)
            down = torch.tensor([DOWN], device=u.device).repeat(num_envs, 1)
            for t in range(steps):
                _, _, _, _, info = env.step(down)
                hit = info["collided"].detach().cpu().bool()
                if not u.gpu_sim_enabled and bool(u.contacts.pairwise().robot_hit.cpu()[0]) != bool(hit[0]):
                    raise AssertionError(f"CPU contact scan and pairwise queries disagree at step {t}")
                first[(first < 0) & hit] = t
                if bool((first >= 0).all()):
                    break
            out += first.tolist()
        finally:
            env.close()
    return out


def contact_verdict(reference: dict[int, int], seeds: Sequence[int], batched: Sequence[int]) -> tuple[bool, str]:
    """``reference``: seed -> first collision step on the CPU scan; ``batched``: per env (seeds tiled) on the
    backend under test. Every env must collide, within one control step of the CPU."""
    if any(v < 0 for v in reference.values()):
        return False, f"the CPU reference never collided: {reference}"
    miss = [i for i, s in enumerate(batched) if s < 0]
    if miss:
        return False, f"{len(miss)} envs never collided (first: env {miss[0]}); CPU: {reference}"
    off = [
        (i, s, reference[seeds[i % len(seeds)]])
        for i, s in enumerate(batched)
        if abs(s - reference[seeds[i % len(seeds)]]) > 1
    ]
    if off:
        i, s, r = off[0]
        return False, f"{len(off)} envs disagree with the CPU scan, first: env {i} at step {s}, CPU at {r}"
    return True, f"all {len(batched)} envs collide within 1 step of the CPU scan (CPU steps {reference})"


def check_contacts(
    sim_backend: str, num_envs: int, seeds: Sequence[int] = COLLISION_SEEDS, env_id: str = TABLE_CLEARING
) -> tuple[bool, str]:
    """The batched contact query (GPU) flags a scripted collision when the CPU contact scan does."""
    steps = 80
    ref = dict(zip(seeds, first_collisions("physx_cpu", 1, seeds, env_id, steps)))
    return contact_verdict(ref, seeds, first_collisions(sim_backend, num_envs, seeds, env_id, steps))


# --------------------------------------------------------------------------- camera frames
def frames_verdict(rgb: torch.Tensor, depth: torch.Tensor, num_envs: int, hw: tuple[int, int] = IMAGE_HW):
    """Batched hand-camera frames: (N, H, W, 3) uint8 RGB and (N, H, W, 1) depth, each env's frame its own (no
    two alike), none blank."""
    if tuple(rgb.shape) != (num_envs, *hw, 3) or tuple(depth.shape) != (num_envs, *hw, 1):
        return (
            False,
            f"rgb {tuple(rgb.shape)}, depth {tuple(depth.shape)}; expected ({num_envs}, {hw[0]}, {hw[1]}, 3/1)",
        )
    if rgb.dtype != torch.uint8:
        return False, f"rgb dtype {rgb.dtype}, expected torch.uint8"
    flat = rgb.reshape(num_envs, -1)
    blank = (flat.amax(1) == 0) | (depth.reshape(num_envs, -1).amax(1) <= 0)
    if bool(blank.any()):
        return (
            False,
            f"{int(blank.sum())} envs' frames are blank (no colour or no depth), e.g. env {int(blank.nonzero()[0])}",
        )
    distinct = len(torch.unique(flat, dim=0))
    if distinct != num_envs:
        return False, f"only {distinct} distinct rgb frames among {num_envs} envs (a frame shared across envs)"
    return True, f"{num_envs} distinct {hw[0]}x{hw[1]} RGB-D frames ({rgb.device})"


def frames_after_random_steps(env: gym.Env, steps: int) -> dict:
    """The hand camera's frames after a seeded reset and ``steps`` seeded random actions."""
    env.reset(seed=0)
    act = random_actions(env, 2)
    for _ in range(steps):
        obs, *_ = env.step(act())
    return obs["sensor_data"][CAMERA]


def check_rgbd_frames(sim_backend: str, num_envs: int, env_id: str = TABLE_CLEARING, steps: int = 2):
    """Batched hand-camera frames have the policy's shape and differ per env (random actions, per-env starts)."""
    env = make(env_id, num_envs, sim_backend, "rgbd")
    try:
        cam = frames_after_random_steps(env, steps)
        return frames_verdict(cam["rgb"], cam["depth"], num_envs)
    finally:
        env.close()


# --------------------------------------------------------------------------- randomised frames of the CPU sim
RANDOMISED_FRAMES = "depth_model=d435,depth_noise=0:5,depth_dropout=0:0.06,texture=1,color=0.3,light=0.4:1.6"
"""every per-frame randomisation (the depth model, noise and dropout) with the appearance ranges"""


def check_randomised_frames(env_id: str = TABLE_CLEARING, steps: int = 2) -> tuple[bool, str]:
    """The CPU sim's randomised camera frames, which on a GPU machine render on CUDA while the sim and its
    randomisation generator stay on the CPU (the CPU-worker trainers' path there; the first randomised camera run
    on an H200 failed at its first frame on that device mismatch). Needs no PhysX GPU library."""
    env = make(env_id, 1, "physx_cpu", "rgbd", randomization=RANDOMISED_FRAMES)
    try:
        cam = frames_after_random_steps(env, steps)
        ok, why = frames_verdict(cam["rgb"], cam["depth"], 1)
        where = "cuda" if env.unwrapped.backend.render_device.is_cuda() else "cpu"
        return ok, f"{why}, CPU physics, rendered on {where}, randomization={RANDOMISED_FRAMES}"
    finally:
        env.close()


# --------------------------------------------------------------------------- appearance randomisation per env
def appearance_verdict(colors: torch.Tensor, textured: torch.Tensor, num_envs: int) -> tuple[bool, str]:
    """(N, 3) the table's colour in each env's own material, (N,) whether each env's table wears a texture: every
    env its own draw (a GPU scene built from one material per builder would show one colour everywhere)."""
    if tuple(colors.shape) != (num_envs, 3) or tuple(textured.shape) != (num_envs,):
        return False, f"table colours {tuple(colors.shape)}, textures {tuple(textured.shape)}; expected {num_envs} envs"
    if not bool(textured.all()):
        return False, f"{int((~textured).sum())} envs' tables have no texture with texture=1"
    distinct = len(torch.unique(colors, dim=0))
    if distinct != num_envs:
        return False, f"only {distinct} distinct table colours among {num_envs} envs (materials shared across envs)"
    return True, f"{num_envs} envs, each table its own colour and texture"


def check_appearance(sim_backend: str, num_envs: int, env_id: str = TABLE_CLEARING) -> tuple[bool, str]:
    """``randomization="texture=1,color=0.3"``: each env's table has its own material, colour and texture."""
    from maniskill_irb120.envs.appearance import render_shapes_per_env

    env = make(env_id, num_envs, sim_backend, "rgbd", randomization="texture=1,color=0.3")
    try:
        env.reset(seed=0)
        shapes = render_shapes_per_env(env.unwrapped.table_scene.table)
        mats = [shapes[i][0].material for i in range(num_envs)]
        colors = torch.tensor([list(m.base_color)[:3] for m in mats])
        textured = torch.tensor([m.base_color_texture is not None for m in mats])
        return appearance_verdict(colors, textured, num_envs)
    finally:
        env.close()


ENV_CHECKS: dict[str, Callable[..., tuple[bool | None, str]]] = {
    "obs modes": check_obs_modes,
    "partial resets": check_partial_resets,
    "controller targets": check_controller_reset,
    "contacts": check_contacts,
    "rgbd frames": check_rgbd_frames,
    "appearance per env": check_appearance,
}
"""the checks that drive the envs, in report order; each takes (sim_backend, num_envs)"""
