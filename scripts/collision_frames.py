"""One collision under a view shift, frame by frame: a camera policy in the sim under a shift, episodes from
``--seed`` upward until one collides, then the same seed with no shift; per step the policy's input images (rgb
and depth, as it sees them), its action, the TCP and object positions, the events and the contacts of the robot
with the scene (which link against which actor, where). Writes ``runs.npz`` under ``--out``, prints a step table
of where the two runs part, and draws ``--figure`` (frames before the collision, shifted over unshifted, and the
TCP height and distances against step).

    PYTHONPATH=. .venv/bin/python scripts/collision_frames.py \\
        --policy teacher-student-sel-tableclearing-s1 --seed 42420000 --max-episodes 8 \\
        --figure docs/notes/screenshots/collision-under-shift.png

The sim env and the policy come from ``sim2real-eval``'s own path (``load_policy`` with the shift as its
``sim_shift``), so a run is the sim side of ``sim2real-eval --sim-shift --shift SPEC`` for that seed.
Deterministic: the shift's draws (view, appearance, per-step depth noise) are seeded by the episode seed.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

COMBINED = "camera_fov=75,light=0.5,color=0.25,texture=1,roughness=0.3,specular=0.8,depth_model=d435"
"""benchmarks/sim2real_gap.py COMBINED's 'fov 75 + light 0.5 + colours/textures + D435'"""
ENV_ID = "TableClearing-IRB120-v1"


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    class Parser(argparse.ArgumentParser):
        def error(self, message):  # one line, exit 2
            print(f"collision_frames.py: {message}", file=sys.stderr)
            raise SystemExit(2)

    p = Parser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", default="teacher-student-sel-tableclearing-s1", help="file or MANIFEST name")
    p.add_argument("--shift", default=COMBINED, help="Randomization.parse syntax (default: sim2real_gap's COMBINED)")
    p.add_argument("--seed", type=int, default=42420000, help="first episode seed")
    p.add_argument("--max-episodes", type=int, default=8, help="shifted episodes to try before giving up")
    p.add_argument("--out", type=Path, default=Path("runs/collision_frames"))
    p.add_argument("--figure", type=Path, default=None, help="PNG to draw (default: OUT/collision-under-shift.png)")
    p.add_argument("--frames", type=int, default=8, help="frames shown per row, ending at the collision step")
    p.add_argument("--stride", type=int, default=3, help="steps between the frames shown")
    a = p.parse_args(argv)
    if a.max_episodes < 1 or a.frames < 1 or a.stride < 1:
        p.error("--max-episodes, --frames and --stride must be at least 1")
    if a.seed < 0:
        p.error(f"--seed {a.seed}: episode seeds are 0 or more")
    from maniskill_irb120.envs.randomization import Randomization

    try:
        Randomization.parse(a.shift)
    except (ValueError, TypeError) as e:
        p.error(f"--shift {a.shift!r}: {e}")
    return a


def _robot_contacts(u) -> list[dict]:
    """Contacts of a robot link (base excluded) with anything but the target object, with their impulse (N s)
    and world points: what the task's ``collided`` reads (envs/scene.py Contacts.scan), named."""
    c = u.contacts
    robot = {link._bodies[0].entity: link.name for link in c.robot_links}
    scene = {a._bodies[0].entity: a.name for a in c.scene_actors}
    out = []
    for ct in u.scene.px.get_contacts():
        e0, e1 = ct.bodies[0].entity, ct.bodies[1].entity
        link, other = (robot.get(e0), e1) if e0 in robot else (robot.get(e1), e0)
        if link is None or other not in scene:
            continue
        imp = sum((p.impulse for p in ct.points), np.zeros(3)) if ct.points else np.zeros(3)
        pts = [list(map(float, p.position)) for p in ct.points]
        out.append(dict(link=link, actor=scene[other], impulse=float(np.linalg.norm(imp)), points=pts))
    return out


def play(policy: str, seed: int, shift: str | None) -> dict:
    """One episode of ``policy`` at ``seed`` under ``shift`` (None: the nominal task), recorded per step."""
    import torch

    from maniskill_irb120.envs.randomization import Randomization
    from maniskill_irb120.sim2real.policy import load_policy

    env, make = load_policy(policy, ENV_ID, "tool_delta", "as-trained", Randomization.parse(shift) if shift else None)
    try:
        pol = make(env)
        obs, info = env.reset(seed=seed)
        pol.reset(seed)
        u = env.unwrapped
        rec: dict[str, list] = {k: [] for k in ("rgb", "depth", "action", "tcp", "obj", "grip_closed", "contacts")}
        events: dict[str, list] = {}
        for _ in range(250):
            rec["rgb"].append(obs["rgb"][0, ..., :3].cpu().numpy().copy())  # what the policy acts on this step
            rec["depth"].append(obs["depth"][0, ..., 0].cpu().numpy().copy())
            a = pol.act(obs)
            obs, _, term, trunc, info = env.step(a)
            rec["action"].append(np.asarray(torch.as_tensor(a).reshape(-1).cpu()))
            rec["tcp"].append(u.agent.tcp_pose.p[0].cpu().numpy().copy())
            rec["obj"].append(u.target_object.pose.p[0].cpu().numpy().copy())
            rec["grip_closed"].append(bool(u.agent.gripper_commanded_closed[0]))
            rec["contacts"].append(_robot_contacts(u))
            for k in ("success", "grasped", "held", "collided", "object_lifted", "object_over_dest", "dropped"):
                if k in info:
                    events.setdefault(k, []).append(bool(info[k][0]))
            if bool(term[0]) or bool(trunc[0]):
                break
        out = {k: np.array(v) for k, v in rec.items() if k != "contacts"}
        out.update({f"ev_{k}": np.array(v) for k, v in events.items()})
        out["contacts"] = rec["contacts"]
        out["source"] = u.source_center[0].cpu().numpy().copy() if hasattr(u, "source_center") else None
        out["dest"] = u.dest_center[0].cpu().numpy().copy() if hasattr(u, "dest_center") else None
        out["steps"] = len(rec["action"])
        return out
    finally:
        env.close()


def table(shifted: dict, nominal: dict, every: int = 1) -> tuple[str, int | None, int | None]:
    """Markdown rows of both runs per step (the TCP after that step's action), the first step after which the
    TCPs are > 5 mm apart, and the first after which their heights are."""
    n = min(shifted["steps"], nominal["steps"])
    gap = np.linalg.norm(shifted["tcp"][:n] - nominal["tcp"][:n], axis=1)
    apart = np.flatnonzero(gap > 0.005)
    first = int(apart[0]) if apart.size else None
    dz = np.flatnonzero(np.abs(shifted["tcp"][:n, 2] - nominal["tcp"][:n, 2]) > 0.005)
    first_z = int(dz[0]) if dz.size else None
    lines = [
        "| step | TCP z shifted / none (mm) | TCP to object shifted / none (mm) | TCP gap (mm) | grip closed s / n |",
        "|---|---|---|---|---|",
    ]
    for t in range(0, shifted["steps"], every):
        if t >= n and t != shifted["steps"] - 1:
            continue
        zs, ds = shifted["tcp"][t, 2] * 1e3, np.linalg.norm(shifted["tcp"][t] - shifted["obj"][t]) * 1e3
        if t < nominal["steps"]:
            zn, dn = nominal["tcp"][t, 2] * 1e3, np.linalg.norm(nominal["tcp"][t] - nominal["obj"][t]) * 1e3
            row = f"| {t} | {zs:.0f} / {zn:.0f} | {ds:.0f} / {dn:.0f} | {gap[t] * 1e3:.0f} | "
            row += f"{int(shifted['grip_closed'][t])} / {int(nominal['grip_closed'][t])} |"
        else:
            row = f"| {t} | {zs:.0f} / – | {ds:.0f} / – | – | {int(shifted['grip_closed'][t])} / – |"
        lines.append(row)
    return "\n".join(lines), first, first_z


def figure(shifted: dict, nominal: dict, path: Path, frames: int, stride: int, first_z: int | None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    end = shifted["steps"] - 1  # the collision step: its input frame is the last the policy acted on
    steps = [s for s in range(end - stride * (frames - 1), end + 1, stride) if s >= 0]
    fig = plt.figure(figsize=(1.45 * len(steps) + 3.6, 6.2), dpi=80)
    gs = fig.add_gridspec(4, len(steps) + 2, width_ratios=[1] * len(steps) + [0.15, 2.3])
    rows = [
        ("shifted rgb", shifted, "rgb"),
        ("shifted depth", shifted, "depth"),
        ("no shift rgb", nominal, "rgb"),
        ("no shift depth", nominal, "depth"),
    ]
    dmax = max(float(np.percentile(nominal["depth"][steps], 99)), 1.0)
    for r, (label, run, key) in enumerate(rows):
        for c, s in enumerate(steps):
            ax = fig.add_subplot(gs[r, c])
            ax.set_xticks([]), ax.set_yticks([])
            if s < run["steps"]:
                img = run[key][s]
                ax.imshow(img, cmap="viridis", vmin=0, vmax=dmax) if key == "depth" else ax.imshow(img)
            if r == 0:
                ax.set_title(f"step {s}", fontsize=8)
            if c == 0:
                ax.set_ylabel(label, fontsize=8)
    ax = fig.add_subplot(gs[:2, -1])
    for run, name, style in ((shifted, "shifted", "-"), (nominal, "no shift", "--")):
        ax.plot(run["tcp"][:, 2] * 1e3, style, color="C0", label=f"TCP z, {name}")
        ax.plot(np.linalg.norm(run["tcp"] - run["obj"], axis=1) * 1e3, style, color="C1", label=f"TCP-object, {name}")
    ax.axvline(end, color="r", lw=0.8)
    if first_z is not None:
        ax.axvline(first_z, color="k", lw=0.8, ls=":")
    ax.set_ylabel("mm", fontsize=8), ax.tick_params(labelsize=7), ax.legend(fontsize=6)
    ax.set_title("red: collision; dotted: TCP heights > 5 mm apart", fontsize=7)
    ax = fig.add_subplot(gs[2:, -1])
    n = min(shifted["steps"], nominal["steps"])
    ax.plot(np.linalg.norm(shifted["tcp"][:n] - nominal["tcp"][:n], axis=1) * 1e3, color="k", label="TCP gap (mm)")
    ax.set_ylim(0, 1.6 * ax.get_ylim()[1])
    ax.set_xlabel("step", fontsize=8), ax.tick_params(labelsize=7)
    ax.set_ylabel("TCP gap, mm", fontsize=8)
    ax2 = ax.twinx()  # action[0]: along the tool's approach axis, here straight down (+1: 1 cm deeper)
    ax2.plot(shifted["action"][:, 0], color="C2", label="approach cmd, shifted")
    ax2.plot(nominal["action"][:, 0], color="C2", ls="--", label="approach cmd, no shift")
    ax2.set_ylim(-1.1, 2.2), ax2.set_yticks([-1, 0, 1]), ax2.tick_params(labelsize=7)
    ax2.set_ylabel("approach action", fontsize=8)
    handles = ax.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
    ax2.legend(handles, [h.get_label() for h in handles], fontsize=6, loc="upper right")
    fig.tight_layout(pad=0.3)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)


def main(argv: list[str] | None = None) -> int:
    a = parse(argv)
    from maniskill_irb120.errors import UsageError
    from maniskill_irb120.policies import read_policy_section
    from maniskill_irb120.sim2real.policy import resolve_policy

    try:  # a wrong --policy: one line, before any env is built
        policy = resolve_policy(a.policy)
        read_policy_section(Path(policy), f"--policy {policy}")
    except UsageError as e:
        print(f"collision_frames.py: {e}", file=sys.stderr)
        return 2
    shifted = None
    for k in range(a.max_episodes):
        seed = a.seed + k
        run = play(policy, seed, a.shift)
        collided = bool(run.get("ev_collided", np.zeros(1)).any())
        print(
            f"seed {seed} shifted: {run['steps']} steps, success {bool(run['ev_success'].any())}, collided {collided}"
        )
        if collided:
            shifted = run
            break
    if shifted is None:
        print(f"no collision in {a.max_episodes} shifted episodes from seed {a.seed}", file=sys.stderr)
        return 1
    nominal = play(policy, seed, None)
    print(f"seed {seed} no shift: {nominal['steps']} steps, success {bool(nominal['ev_success'].any())}")
    rows, first, first_z = table(shifted, nominal)
    hit = int(np.flatnonzero(shifted["ev_collided"])[0])
    contacts = [c for c in shifted["contacts"][hit] if c["impulse"] > 0]
    print(rows)
    summary = dict(seed=seed, collision_step=hit, tcps_apart_from=first, heights_apart_from=first_z)
    print(json.dumps(dict(summary, contacts=[{k: c[k] for k in ("link", "actor", "impulse")} for c in contacts])))
    a.out.mkdir(parents=True, exist_ok=True)
    save = {
        f"{side}_{k}": v
        for side, r in (("shifted", shifted), ("nominal", nominal))
        for k, v in r.items()
        if isinstance(v, np.ndarray)
    }
    np.savez_compressed(a.out / "runs.npz", seed=seed, **save)
    (a.out / "contacts.json").write_text(json.dumps(dict(shifted=shifted["contacts"], nominal=nominal["contacts"])))
    figure(shifted, nominal, a.figure or a.out / "collision-under-shift.png", a.frames, a.stride, first_z)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
