"""The staged rewards (``normalized_dense``, the default) lead to success: along the scripted expert's
trajectory the stage (``floor(4 · reward)``: envs/base.py ``MAX_STAGED_REWARD``) never goes back and each stage
enters above the last one's best, and no stall (hovering at the grasp height, holding the object, pushing it,
colliding at once) earns more than succeeding. Success ends the episode; as in ManiSkill (and agents/ppo.py,
which bootstraps it), it counts as absorbing: 1 per step to the time limit."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

import maniskill_irb120  # noqa: F401
from maniskill_irb120.action import action_from_world_motion, tcp_rotation
from maniskill_irb120.experts.pick_place import CARRY, CLOSE, HOLD, RELEASE, expert_for

HORIZON = {"TableClearing-IRB120-v1": 250, "GraspLift-IRB120-v1": 150, "StackCube-IRB120-v1": 200}
HOLD_STALL = {"TableClearing-IRB120-v1": CARRY, "GraspLift-IRB120-v1": HOLD, "StackCube-IRB120-v1": RELEASE}
SEEDS = (0, 1)


def _world(env, disp, gripper: float) -> torch.Tensor:
    u = env.unwrapped
    d = torch.tensor([disp], dtype=torch.float32, device=u.device)
    return action_from_world_motion(
        d,
        torch.zeros(1, device=u.device),
        torch.tensor([gripper], device=u.device),
        tcp_rotation(u.agent.tcp_pose.raw_pose),
    )


def _expert_until(env, phase: int):
    """The scripted expert, stepped from the current state until it would act in ``phase`` (not stepped there)."""
    expert = expert_for(env)
    expert.reset()
    while True:
        action = expert.act()
        if int(expert.phase[0]) == phase:
            return expert
        env.step(action)


def rollout(env, seed: int, stall: str | None = None, grip: float = -1.0) -> tuple[list[float], dict]:
    """Per-step rewards and the last info of the expert, or of a stall: the expert until the stall's phase,
    then ``hover`` (still, open, at the grasp height), ``push`` (open, back and forth along x by 2.5 cm),
    ``hold`` (closed: still over the source tray or over cube_b; GraspLift: bobbing 4 mm, never still),
    ``hold at place`` (TableClearing: closed and still where the expert would open the fingers; ``grip``: the
    gripper command it holds with, <= 0 keeps the fingers shut),
    ``collide`` (straight down from the start until a link hits the scene)."""
    env.reset(seed=seed)
    expert = expert_for(env)
    expert.reset()
    env_id = env.unwrapped.spec.id
    rewards, latched, k, info = [], False, 0, {}
    for _ in range(HORIZON[env_id]):
        if stall == "collide":
            action = _world(env, [0, 0, -0.01], 1.0)
        else:
            action = expert.act()
            phase = int(expert.phase[0])
            stall_phase = {"hold": HOLD_STALL[env_id], "hold at place": RELEASE}.get(stall, CLOSE)
            latched |= phase == stall_phase and stall is not None
            if latched:
                k += 1
                if stall == "hover":
                    action = _world(env, [0, 0, 0], 1.0)
                elif stall == "push":
                    action = _world(env, [0.005 if (k // 5) % 2 == 0 else -0.005, 0, 0], 1.0)
                elif env_id == "GraspLift-IRB120-v1":
                    action = _world(env, [0, 0, 0.004 if k % 2 else -0.004], -1.0)
                else:
                    action = _world(env, [0, 0, 0], grip)
        _, r, term, trunc, info = env.step(action)
        rewards.append(float(r[0]))
        if bool(term[0]) or bool(trunc[0]):
            break
    return rewards, info


def absorbing_return(env_id: str, rewards: list[float], info: dict) -> float:
    """The return with success absorbing (1 per step to the time limit)."""
    return sum(rewards) + (HORIZON[env_id] - len(rewards)) * float(info["success"][0])


@pytest.fixture(scope="module")
def envs():
    """``envs(env_id)``: this file's one env of that task (state obs, ``pd_ee_delta_tool``), built on first use."""
    import gymnasium as gym

    made = {}

    def get(env_id: str):
        if env_id not in made:
            made[env_id] = gym.make(env_id, obs_mode="state", control_mode="pd_ee_delta_tool")
        return made[env_id]

    yield get
    for env in made.values():
        env.close()


@pytest.fixture(scope="module")
def rollouts(envs):
    """``rollouts(env_id, seed, stall=None, grip=-1.0)``: :func:`rollout` in that task's env, run once per file (an
    episode is its seed's alone: the expert's runs, the "hold" stalls and "hold at place" serve several tests)."""
    done = {}

    def get(env_id: str, seed: int, stall: str | None = None, grip: float = -1.0) -> tuple[list[float], dict]:
        key = (env_id, seed, stall, grip)
        if key not in done:
            done[key] = rollout(envs(env_id), seed, stall, grip)
        return done[key]

    return get


@pytest.fixture(scope="module", params=sorted(HORIZON))
def task(request, envs):
    return request.param, envs(request.param)


@pytest.fixture(scope="module")
def expert_runs(task, rollouts):
    return [rollouts(task[0], s) for s in SEEDS]


def test_rewards_stay_in_the_unit_interval_and_success_pays_one(expert_runs):
    for rewards, info in expert_runs:
        assert bool(info["success"][0]) and rewards[-1] == 1.0
        assert all(0.0 <= r <= 1.0 for r in rewards)
        assert all(r < 1.0 for r in rewards[:-1])


def test_expert_stages_rise_and_each_enters_above_the_last(expert_runs):
    for rewards, _ in expert_runs:
        stages = [math.floor(4 * r) for r in rewards]
        assert stages == sorted(stages), stages  # never back to an earlier stage
        assert len(set(stages)) >= 3, stages  # reach, at least one middle stage, success
        for i in range(1, len(rewards)):
            if stages[i] > stages[i - 1]:
                assert rewards[i] > max(rewards[:i]), (i, rewards[i - 1 : i + 1])


@pytest.mark.parametrize("stall", ["hover", "push", "hold", "collide"])
def test_no_stall_pays_more_than_success(task, expert_runs, rollouts, stall):
    env_id, _ = task
    for seed, (rewards, info) in zip(SEEDS, expert_runs):
        s_rewards, s_info = rollouts(env_id, seed, stall)
        assert not bool(s_info["success"][0]), (stall, seed)
        assert max(s_rewards) < 1.0  # no stalling state pays per step what the final stage does
        assert sum(s_rewards) < absorbing_return(env_id, rewards, info), (stall, seed)
        if stall == "collide":
            assert bool(s_info["fail"][0]) and s_rewards[-1] == 0.0
            hold_rewards, _ = rollouts(env_id, seed, "hold")  # an episode that grasps beats colliding
            assert sum(s_rewards) < sum(hold_rewards)


def test_the_approach_term_resolves_millimetres_and_degrees_near_the_grasp():
    """The reach stage must tell a grasp pose from one the open fingers cannot close on (3 mm of clearance
    per side for a 20 mm cube): with a plain ``1 - tanh(3·d)`` being 3 mm off cost 0.002 of the normalised
    reward, which is why PPO from scratch approached and never grasped."""
    from mani_skill.utils.geometry.rotation_conversions import quaternion_multiply

    from maniskill_irb120.envs.base import GRASP_POINT_OFFSET, grasp_approach_reward, yaw_quat

    obj = torch.tensor([[0.35, 0.13, 0.015, 1.0, 0.0, 0.0, 0.0]]).repeat(6, 1)
    down = torch.tensor([0.0, 1.0, 0.0, 0.0])  # approach axis (+x) pointing down: 180° about world y
    tcp = torch.zeros(6, 7)
    tcp[:, :3] = obj[:, :3] + torch.tensor([0, 0, GRASP_POINT_OFFSET])
    tcp[:, 3:] = down
    tcp[1, 0] += 0.003  # 3 mm beside the grasp point
    tcp[2, 3:] = quaternion_multiply(yaw_quat(torch.tensor([math.radians(15)])), down[None])[0]  # fingers turned 15°
    tcp[3, 2] += 0.06  # hovering 6 cm above, aligned
    tcp[4, :2] += 0.03  # 3 cm beside, at the grasp height
    tcp[5, :3] = torch.tensor([0.35, 0.0, 0.25])  # the rest pose
    r = grasp_approach_reward(obj, tcp) / 4  # as normalized_dense pays it
    at_grasp, beside, turned, hover, far_side, rest = r.tolist()
    assert 0.249 < at_grasp < 0.25
    assert at_grasp - beside > 0.015 and at_grasp - turned > 0.03  # 7x and 15x the plain distance's 0.002
    assert at_grasp > hover > far_side > rest > 0.0  # rises along the expert's approach
    assert hover - far_side > 0.04  # aligning above it pays before descending does


def test_grasp_yaw_error_is_the_rotation_matrices_angle():
    """The fused form (eleven matrix entries from the quaternions' outer products) against the full rotation
    matrices it replaced, on arbitrary orientations, tilted objects and unnormalised quaternions."""
    from mani_skill.utils.geometry.rotation_conversions import quaternion_to_matrix

    from maniskill_irb120.envs.base import grasp_yaw_error

    def reference(obj_pose, tcp_pose):
        obj_rot, tcp_rot = quaternion_to_matrix(obj_pose[:, 3:]), quaternion_to_matrix(tcp_pose[:, 3:])
        axis_idx = obj_rot[:, 2, :].abs().argmin(dim=1)
        normal = torch.gather(obj_rot, 2, axis_idx.view(-1, 1, 1).expand(-1, 3, 1)).squeeze(2)
        fingers = tcp_rot[:, :, 1]
        delta = torch.atan2(normal[:, 1], normal[:, 0]) - torch.atan2(fingers[:, 1], fingers[:, 0])
        return torch.remainder(delta + math.pi / 4, math.pi / 2) - math.pi / 4

    g = torch.Generator().manual_seed(0)
    obj, tcp = torch.randn(2000, 7, generator=g), torch.randn(2000, 7, generator=g)  # |q| != 1 on purpose
    tcp[:1000, 3:] = torch.tensor([0.0, 1.0, 0.0, 0.0]) + 0.05 * tcp[:1000, 3:]  # near the grasp's pointing down
    got, want = grasp_yaw_error(obj, tcp), reference(obj, tcp)
    wrap = torch.remainder(got - want + math.pi / 4, math.pi / 2) - math.pi / 4  # ±π/4 are the same turn
    assert float(wrap.abs().max()) < 1e-4
    assert float(got.min()) >= -math.pi / 4 and float(got.max()) < math.pi / 4


@pytest.mark.parametrize(
    "env_id, key", [("TableClearing-IRB120-v1", "obj_pose"), ("StackCube-IRB120-v1", "cube_a_pose")]
)
def test_the_grasp_yaw_error_is_computed_once_a_step_and_observed_as_a_copy(monkeypatch, env_id, key):
    """The state observation and the reach reward read one computation per step state; writing into the
    observation does not move what the reward read."""
    import gymnasium as gym

    from maniskill_irb120.envs import base

    env = gym.make(env_id, obs_mode="state_dict", render_backend="none")
    calls = []
    real = base.grasp_yaw_error
    monkeypatch.setattr(base, "grasp_yaw_error", lambda o, t: calls.append(1) or real(o, t))
    try:
        env.reset(seed=0)
        for step in range(3):
            calls.clear()
            obs, *_ = env.step(env.action_space.sample() * 0.3)
            state = env.unwrapped.step_state
            assert len(calls) == 1, f"step {step}: computed {len(calls)} times"
            observed = next(v for k, v in obs["extra"].items() if k.endswith("_yaw"))[:, 0]
            assert torch.equal(observed, real(state[key], state["tcp_pose"]))
            observed += 1.0
            assert torch.equal(state[("grasp_yaw_error", key)], real(state[key], state["tcp_pose"]))
    finally:
        env.close()


def test_holding_the_object_at_its_place_pays_clearly_less_than_letting_go(rollouts):
    """TableClearing's last stage: the expert carried the object into the destination tray and lowered it; held
    there, closed and still, each step pays at most 3.5 of 4 (normalised 0.875), so the one action left,
    opening the fingers, gains >= 0.1 a step. With the full band holding paid 0.99 and PPO held on for good."""
    for seed in SEEDS:
        rewards, info = rollouts("TableClearing-IRB120-v1", seed, "hold at place")
        assert not bool(info["success"][0]) and bool(info["object_over_dest"][0]) and bool(info["held"][0])
        assert math.floor(4 * rewards[-1]) == 3  # the last stage before success, reached
        assert max(rewards) <= 0.875 and 1.0 - rewards[-1] >= 0.1, rewards[-5:]


def test_letting_go_above_the_destination_tray_never_steps_down(envs):
    """TableClearing: the expert carries the object over the destination tray at its carry height (~11 cm above
    the floor) and opens the fingers there instead of lowering it first. The object falls for two control steps;
    when a falling object paid the reach stage (~0.2 against ~0.84 held), PPO (gamma 0.8) learned to hold on."""
    from maniskill_irb120.experts.pick_place import LOWER

    env = envs("TableClearing-IRB120-v1")
    for seed in SEEDS:
        env.reset(seed=seed)
        expert = expert_for(env)
        expert.reset()
        rewards, released, info = [], None, {}
        for _ in range(HORIZON["TableClearing-IRB120-v1"]):
            action = expert.act()
            if released is None and int(expert.phase[0]) == LOWER:
                released = len(rewards)  # the carry ended over the tray: open there from now on
            if released is not None:
                action = _world(env, [0, 0, 0], 1.0)
            _, r, term, trunc, info = env.step(action)
            rewards.append(float(r[0]))
            if released is not None and len(rewards) == released + 1:
                assert not bool(info["held"][0]) and bool(info["object_over_dest"][0])
                assert env.unwrapped.obj.pose.p[0, 2] > 0.08  # let go well above the walls (3 cm)
            if bool(term[0]) or bool(trunc[0]):
                break
        assert released is not None and bool(info["success"][0]) and rewards[-1] == 1.0
        held = rewards[released - 1]
        assert math.floor(4 * held) == 3, held  # held over the tray: the last stage before success
        falling = rewards[released:]
        assert len(falling) >= 2 and all(b >= a for a, b in zip([held, *falling], falling)), (held, falling)


def test_at_its_place_a_gripper_command_nearer_open_pays_more_while_the_fingers_stay_shut(rollouts):
    """The release term: the gripper is one thresholded action, so a policy that keeps it shut for the whole carry
    gets no signal from the fingers at the place until it happens to sample "open"; the command's own approach to
    the threshold pays there (ManiSkill's StackCube "ungrasp", for a binary gripper), below letting go."""
    env_id = "TableClearing-IRB120-v1"
    for seed in SEEDS:
        shut, _ = rollouts(env_id, seed, "hold at place", grip=-1.0)
        nearly, info = rollouts(env_id, seed, "hold at place", grip=-0.05)
        assert bool(info["held"][0]) and not bool(info["success"][0])  # -0.05 is still "close"
        assert nearly[-1] >= shut[-1] + 0.02, (shut[-1], nearly[-1])  # (1/4 · 0.475 · place) / 4
        assert max(nearly) <= 0.9375 and 1.0 - nearly[-1] >= 0.05
        expert, info = rollouts(env_id, seed)  # letting go still pays more than either
        assert bool(info["success"][0]) and expert[-1] == 1.0


def test_the_place_term_resolves_millimetres_over_cube_b():
    """StackCube's stage 1 (cube_a grasped) pays the aligned reach of cube_b's top: the stack test needs cube_a
    within 8 mm across and 4 mm in height, where the first version's ``1 - tanh(3·d)`` was flat (5 mm off cost
    0.0035 of the normalised reward) and PPO from scratch grasped in half its episodes and never stacked."""
    from maniskill_irb120.envs.base import aligned_reach_reward, reach_reward

    goal = torch.tensor([[0.35, 0.13, 0.05]])
    here = goal.repeat(6, 1)
    here[1, 0] += 0.005  # 5 mm beside the place
    here[2, 2] += 0.004  # 4 mm above it: still stacks
    here[3, 2] += 0.03  # 3 cm above, aligned: where the expert lowers from
    here[4, :2] += 0.03  # 3 cm beside, at the place's height (lowered beside cube_b: knocks it)
    here[5] += torch.tensor([-0.05, 0.1, 0.1])  # just lifted from the grasp
    r = aligned_reach_reward(goal - here) / 4  # as normalized_dense pays it (stage 1 adds 1/4 to it)
    at, beside, above_4mm, above, far_side, lifted = r.tolist()
    assert 0.249 < at < 0.25
    plain = reach_reward(torch.tensor([0.0, 0.005])).clamp(max=0.999) / 4
    assert float(plain[0] - plain[1]) < 0.004 and at - beside > 0.02  # > 5x the plain term's difference
    assert at > above_4mm > above > far_side > lifted > 0.0  # rises along the expert's carry and lowering
    assert above - far_side > 0.04  # aligning over cube_b pays before lowering does


def test_stacked_and_held_a_gripper_command_nearer_open_pays_more(envs, rollouts):
    """StackCube's stage 2: with cube_a held on cube_b the one action left is opening the fingers; the gripper
    command's approach to the threshold pays there (a quarter of a band), still below opening (2.5 of 4). The
    expert lets go 3-5 mm above the stack's height; here it goes on holding, lowered onto cube_b."""

    def hold_on_b(env, seed: int, grip: float) -> tuple[list[float], dict]:
        env.reset(seed=seed)
        expert = expert_for(env)
        expert.reset()
        rewards, lowered = [], 0
        for _ in range(60):
            action = expert.act()
            if int(expert.phase[0]) == RELEASE or lowered:
                lowered += 1
                action = _world(env, [0, 0, -0.002 if lowered <= 4 else 0.0], grip)
            _, r, term, trunc, info = env.step(action)
            rewards.append(float(r[0]))
            assert not bool(term[0] or trunc[0])
        return rewards, info

    env = envs("StackCube-IRB120-v1")
    for seed in SEEDS:
        shut, _ = hold_on_b(env, seed, grip=-1.0)
        nearly, info = hold_on_b(env, seed, grip=-0.05)
        assert bool(info["stacked"][0]) and bool(info["grasped"][0]) and not bool(info["success"][0])
        assert shut[-1] == 0.5  # stage 2, commanding "close": 2 of 4
        assert nearly[-1] >= shut[-1] + 0.02 and max(nearly) < 2.5 / 4, (shut[-1], nearly[-1])
        expert, info = rollouts("StackCube-IRB120-v1", seed)  # letting go still pays more than either
        assert bool(info["success"][0]) and expert[-1] == 1.0


def test_a_cube_wedged_between_the_open_fingers_is_no_grasp():
    """SAC from the reward alone learned to push the open fingers down on a cube yawed ~23 degrees off them: the
    26 mm opening wedges the 20 mm cube (its diagonal is 28 mm), both fingers push on it along their closing
    direction, and the contact test alone called it a grasp for 117 of the 150 steps, paying the lift stage for
    an open gripper. Its actions, replayed open loop (tests/envs/data): the fingers still squeeze, but with the
    gripper commanded open it is no grasp and the reward stays in the reach stage."""
    import gymnasium as gym

    from maniskill_irb120.wrappers import WorldFrameToolAction

    rec = json.loads((Path(__file__).parent / "data" / "sac_wedge_grasplift.json").read_text())
    env = WorldFrameToolAction(
        gym.make(rec["env_id"], obs_mode="state", control_mode="pd_ee_delta_tool", render_backend="none")
    )
    try:
        env.reset(seed=rec["seed"])
        u = env.unwrapped
        squeezed = grasped = 0
        rewards = []
        for a in rec["actions"]:
            _, r, term, trunc, info = env.step(torch.tensor([a]))
            forces = u.contacts.flags().finger_forces[0]
            squeeze = bool(u.agent.is_grasping(None, finger_forces=(forces[0], forces[1]))[0])
            squeezed += squeeze and float(u.agent.gripper_opening[0]) > 0.025  # pushed on, fingers wide open
            grasped += bool(info["grasped"][0])
            rewards.append(float(r[0]))
            if bool(term[0]) or bool(trunc[0]):
                break
        assert squeezed > 50  # the wedge: the fingers open, both pushing on the cube
        assert grasped == 0 and max(rewards) < 0.25  # never the grasp stage (normalised: stage 1 starts at 0.25)
    finally:
        env.close()


@pytest.mark.parametrize("seed", SEEDS)
def test_table_clearing_pays_no_grasp_stage_for_a_wedge_it_lifts(seed):
    """The same wedge on TableClearing: the expert brings the open fingers over the object, the object is turned
    25 degrees off them, and the fingers, still commanded open, push down on it and rise. They jam it and lift it
    above 5 cm: the original report's contact-only grasp holds (``grasped``), but the staged reward
    needs the gripper commanded closed for its grasp stages and stays in the reach stage."""
    import gymnasium as gym
    from mani_skill.utils.structs.pose import Pose
    from transforms3d.euler import euler2quat
    from transforms3d.quaternions import qmult

    from maniskill_irb120.experts.pick_place import DESCEND

    env = gym.make("TableClearing-IRB120-v1", obs_mode="state", control_mode="pd_ee_delta_tool", render_backend="none")
    try:
        env.reset(seed=seed)
        u = env.unwrapped
        _expert_until(env, DESCEND)  # the expert's approach: over the object, fingers open and aligned
        obj = u.obj.pose
        q = qmult(euler2quat(0, 0, math.radians(25)), obj.q[0].cpu().numpy())
        u.obj.set_pose(Pose.create_from_pq(obj.p, torch.as_tensor(q, dtype=torch.float32)[None]))
        held = lifted_held = 0
        rewards, pushing = [], True
        for _ in range(100):
            to_obj = (u.obj.pose.p[0] - u.agent.tcp_pose.p[0]).clamp(-0.004, 0.004)
            pushing &= float(u.agent.tcp_pose.p[0, 2]) >= 0.018  # down to 3 mm above the object's centre
            _, r, term, trunc, info = env.step(_world(env, [*to_obj[:2].tolist(), -0.004 if pushing else 0.004], 1.0))
            held += bool(info["held"][0])
            lifted_held += bool(info["grasped"][0])
            rewards.append(float(r[0]))
            assert not bool(term[0] or trunc[0])
        assert held > 50 and lifted_held > 20  # the wedge: open fingers hold the object above 5 cm
        assert max(rewards) < 0.25  # never a grasp stage (normalised: stage 1 starts at 0.25)
    finally:
        env.close()


def test_grasp_lift_hold_stage_pays_for_slowing_down_not_for_a_refused_command():
    """GraspLift's hold stage paid only the count of still steps, flat (2 of 4) for anything moving faster than
    2 cm/s, so nothing taught PPO to slow down: a policy got still by driving the held object at full speed until
    the IK refused every further target and the arm froze (here: straight up to the reach limit), and 20 frozen
    steps made a success. From the expert's lifted grasp: a slower bob pays more, a still hold counts, and an arm
    frozen by refused commands, though its object moves slower than "still", neither counts nor earns the settle
    term, and never succeeds."""
    import gymnasium as gym

    from maniskill_irb120.envs.grasp_lift import HOLD_STEPS, STILL_SPEED

    env = gym.make("GraspLift-IRB120-v1", obs_mode="state", control_mode="pd_ee_delta_tool", render_backend="none")
    u = env.unwrapped

    def run(lifted: dict, actions: list) -> list[tuple[float, dict]]:
        """Per-step rewards and infos of ``actions`` from ``lifted`` (past the time limit: the state is restored,
        the step count is not)."""
        u.set_state_dict(lifted)
        out = []
        for a in actions:
            _, r, term, _, info = env.step(a)
            assert bool(info["grasped"][0] and info["lifted"][0]) and not bool(term[0])
            out.append((float(r[0]), info))
        return out

    try:
        for seed in SEEDS:
            env.reset(seed=seed)
            _expert_until(env, HOLD)
            lifted = u.get_state_dict()

            bob = {}
            for mm in (8, 4, 2):  # up and down by mm each step: 16, 8, 4 cm/s, never "still"
                moves = [_world(env, [0, 0, (-1) ** k * mm / 1000], -1.0) for k in range(6)]
                steps = run(lifted, moves)
                assert all(int(i["hold_steps"][0]) == 0 for _, i in steps)
                bob[mm] = steps[-1][0]
            assert bob[8] < bob[4] < bob[2] < 0.75, bob  # slower pays more, all inside the hold stage's band

            still = run(lifted, [_world(env, [0, 0, 0], -1.0)] * 10)
            assert [int(i["hold_steps"][0]) for _, i in still][-3:] == [8, 9, 10]  # one count per still step
            assert min(r for r, _ in still[2:]) > bob[2]

            up = torch.tensor([[-1.0, 0, 0, 0, -1.0]])  # tool -x: straight up, past the 0.58 m reach
            pushed = run(lifted, [up] * (62 + HOLD_STEPS))
            frozen = [
                (r, i) for r, i in pushed if bool(i["ik_unreachable"][0]) and float(i["object_speed"][0]) < STILL_SPEED
            ]
            assert len(frozen) >= HOLD_STEPS, "the push never froze the arm at the reach limit for a second"
            for r, i in frozen:
                assert not bool(i["still"][0]) and int(i["hold_steps"][0]) == 0 and not bool(i["success"][0])
                assert r == pytest.approx(2 / 4, abs=1e-6)  # the lifted stage's floor: no settle, no count
    finally:
        env.close()
