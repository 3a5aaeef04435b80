"""``report.json`` and ``report.md`` (+ small PNGs) for ``sim2real-eval``: rates per side, deviations, latency,
refusals; TCP paths sim vs real overlaid, hand-camera frames side by side, deviation over time."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

PLOT_EPISODES = 4


def write_report(out: Path, report: dict, rows: list) -> None:
    (out / "report.json").write_text(json.dumps(report, indent=2))
    pictures = _plots(out, rows) if rows else []
    (out / "report.md").write_text(_markdown(report, pictures))


def _fmt(x, pct: bool = False) -> str:
    if x is None:
        return "–"
    return f"{100 * x:.0f} %" if pct else f"{x:.3g}"


def _markdown(r: dict, pictures: list[str]) -> str:
    c = r["config"]
    lines = [
        f"# sim vs real: {c['env_id']}, policy `{c['policy']}`, robot `{c['robot']}`",
        "",
        f"{r['episodes']} episodes from seed {c['seed']}; shift: `{c['shift']}`; "
        f"{r['wall_clock_s']:.0f} s{' (interrupted)' if r['interrupted'] else ''}.",
        "",
        "| | success | grasp | drop | collision | mean steps |",
        "|---|---|---|---|---|---|",
    ]
    for side in ("sim", "real"):
        s = r[side]
        cells = " | ".join(_fmt(s[k], pct=True) for k in ("success", "grasped", "dropped", "collided"))
        lines.append(f"| {side} | {cells} | {r['mean_steps'][side]:.1f} |")
    if r["unscored_real"]:
        lines.append(f"\n{r['unscored_real']} real episodes were not scored by the operator.")
    lines += ["", "| per step, same step index | mean | p50 | p95 | max |", "|---|---|---|---|---|"]
    names = dict(tcp_m="TCP distance (m)", joint_rad="largest joint difference (rad)", action="action difference (L2)")
    for key, label in names.items():
        d = r["deviation"][key]
        lines.append(f"| {label} | " + " | ".join(_fmt(d.get(k)) for k in ("mean", "p50", "p95", "max")) + " |")
    lat = r["command_latency_ms"]
    lines += [
        "",
        "Command round trip (ms): " + ", ".join(f"{k} {_fmt(v)}" for k, v in lat.items()),
        "",
        f"Refused commands: {r['refused']['total']} {r['refused']['by_limit'] or ''}",
        f"Steps the robot had not finished within the arrival bound: {r['late_steps']}",
        "",
    ]
    lines += [f"![{Path(p).stem}]({p})" for p in pictures]
    return "\n".join(lines) + "\n"


def _plots(out: Path, rows: list) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    fig, axes = plt.subplots(1, 2, figsize=(8, 3.6), dpi=80)
    for i, row in enumerate(rows[:PLOT_EPISODES]):
        for side, style in (("sim", "-"), ("real", "--")):
            p = row[side]["tcp"]
            if len(p):
                label = f"{side} {row['seed']}"
                axes[0].plot(p[:, 0], p[:, 1], style, color=f"C{i}", label=label)
                axes[1].plot(p[:, 0], p[:, 2], style, color=f"C{i}")
    axes[0].set(xlabel="x (m)", ylabel="y (m)", title="TCP path, top view")
    axes[1].set(xlabel="x (m)", ylabel="z (m)", title="side view")
    axes[0].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "tcp_paths.png")
    plt.close(fig)
    names.append("tcp_paths.png")

    fig, ax = plt.subplots(figsize=(6, 3), dpi=80)
    for i, row in enumerate(rows[:PLOT_EPISODES]):
        ax.plot(1000 * row["deviation"]["tcp_m"], color=f"C{i}", label=f"seed {row['seed']}")
    ax.set(xlabel="step", ylabel="TCP sim - real (mm)", title="deviation over time")
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "deviation.png")
    plt.close(fig)
    names.append("deviation.png")

    sim_frames, real_frames = rows[0]["sim"]["frames"], rows[0]["real"]["frames"]
    if sim_frames and real_frames:
        n = min(len(sim_frames), len(real_frames))
        fig, axes = plt.subplots(2, n, figsize=(1.6 * n, 3.4), dpi=80, squeeze=False)
        for j in range(n):
            for k, (side, frames) in enumerate((("sim", sim_frames), ("real", real_frames))):
                axes[k, j].imshow(np.asarray(frames[j]))
                axes[k, j].set_axis_off()
                axes[k, j].set_title(f"{side} {('start', 'step 30', 'end')[j] if n == 3 else j}", fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "hand_camera.png")
        plt.close(fig)
        names.append("hand_camera.png")
    return names


def agreement(sim: list[float], real: list[float]) -> dict:
    """How well the sim's success rates predict the real side's over paired evaluations (checkpoints x shifts), as
    SimplerEnv reports it. MMRV (mean maximum rank violation, 0 = the sim orders every pair as the real side does):
    for each evaluation i, the largest real-success gap |R_i - R_j| among the evaluations j the sim orders the
    other way round, averaged over i. Pearson r of the two success vectors: None when either side is constant
    (a single checkpoint against nominal sim seeds has one sim rate for every shift)."""
    s, r = np.asarray(sim, dtype=np.float64), np.asarray(real, dtype=np.float64)
    if s.shape != r.shape or s.ndim != 1 or len(s) < 2:
        raise ValueError(f"agreement needs two equal-length lists of >= 2 success rates, got {s.shape} and {r.shape}")
    if not (np.isfinite(s).all() and np.isfinite(r).all()):
        raise ValueError("agreement: success rates must be finite (an unscored real episode has no rate)")
    violated = (s[:, None] < s[None, :]) != (r[:, None] < r[None, :])
    mmrv = float((np.abs(r[:, None] - r[None, :]) * violated).max(axis=1).mean())
    pearson = None if np.ptp(s) == 0 or np.ptp(r) == 0 else float(np.corrcoef(s, r)[0, 1])
    return dict(mmrv=mmrv, pearson=pearson, pairs=len(s))


def paired_gap(per_episode: list[dict]) -> dict:
    """Whether a cell's sim/real difference is more than chance: both sides ran the same seeds, so only the
    discordant episodes (success on one side only) carry evidence, and McNemar's exact test asks whether they
    split unevenly (two-sided binomial on them at 1/2). Thirty episodes leave wide margins: 5 against 1 is
    p = 0.22. Episodes the real side could not score are left out."""
    from scipy.stats import binomtest

    scored = [e for e in per_episode if e["sim_success"] is not None and e["real_success"] is not None]
    sim_only = sum(bool(e["sim_success"]) and not e["real_success"] for e in scored)
    real_only = sum(bool(e["real_success"]) and not e["sim_success"] for e in scored)
    n = sim_only + real_only
    p = float(binomtest(sim_only, n, 0.5).pvalue) if n else 1.0
    return dict(sim_only=sim_only, real_only=real_only, mcnemar_p=p, episodes=len(scored))
