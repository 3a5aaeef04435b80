"""Expert demonstrations in ManiSkill's trajectory format (h5 + json), via ManiSkill's RecordEpisode.

The json names the env as ``maniskill_irb120:<env id>``, so ManiSkill's own replay tool finds it in a
fresh interpreter with no import of ours::

    python -m mani_skill.trajectory.replay_trajectory --traj-path demos/expert.h5 --use-env-states
"""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
from mani_skill.utils.wrappers.record import RecordEpisode

import maniskill_irb120  # noqa: F401
from maniskill_irb120.envs.table_clearing import ENV_ID as DEFAULT_ENV_ID
from maniskill_irb120.experts import expert_for
from maniskill_irb120.experts.rollout import run_episode


def collect_demos(
    episodes: int = 10,
    seed: int = 0,
    out_dir: Path = Path("demos"),
    name: str = "expert",
    obs_mode: str = "none",
    only_success: bool = True,
    save_video: bool = False,
    env_id: str = DEFAULT_ENV_ID,
    **env_kwargs,
) -> dict:
    """Roll out the task's expert for seeds ``seed..seed+episodes-1`` and record each episode.

    ``only_success`` drops failed episodes from the file (ManiSkill's convention for demo sets). The
    recorded rewards are the task's ``dense`` ones. Returns the paths and counts; raises if nothing was kept.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    out_dir = Path(out_dir)
    env = gym.make(
        env_id,
        obs_mode=obs_mode,
        control_mode="pd_ee_delta_tool",
        reward_mode="dense",
        render_mode="rgb_array" if save_video else None,
        **env_kwargs,
    )
    expert = expert_for(env)
    env = RecordEpisode(
        env,
        output_dir=str(out_dir),
        trajectory_name=name,
        save_video=save_video,
        save_on_reset=False,
        record_env_state=True,
        video_fps=20,
        source_type="motion_planning",
        source_desc="maniskill_irb120 scripted expert",
    )
    kept = 0
    for ep in range(episodes):
        keep = run_episode(env, expert, seed + ep).success or not only_success
        env.flush_trajectory(save=keep)
        if save_video:
            env.flush_video(save=keep)
        kept += keep
    env.close()
    h5, js = out_dir / f"{name}.h5", out_dir / f"{name}.json"
    if kept == 0:
        raise RuntimeError(f"no successful episode among {episodes}; nothing recorded")
    meta = json.loads(js.read_text())
    meta["env_info"]["env_id"] = f"maniskill_irb120:{env_id}"
    js.write_text(json.dumps(meta, indent=2))
    return dict(env_id=env_id, h5=str(h5), json=str(js), episodes_recorded=kept, episodes_tried=episodes)
