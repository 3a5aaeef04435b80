"""Demo: the scripted expert clears the table on CPU; one mp4 shows the overview camera beside the
84x84 hand camera, a PNG shows the scene, and the success rate and step timing are printed.

    .venv/bin/python examples/demo.py [--env-id TableClearing-IRB120-v1] [--episodes 3] [--seed 0] [--out-dir outputs]
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import imageio.v2 as imageio
import numpy as np
import torch

import maniskill_irb120  # noqa: F401
from maniskill_irb120.envs import check_env_id
from maniskill_irb120.errors import check_count, parse_flags, usage_errors
from maniskill_irb120.experts import expert_for
from maniskill_irb120.experts.rollout import run_episode


@dataclass
class Args:
    env_id: str = "TableClearing-IRB120-v1"
    """any task with a scripted expert: TableClearing-, GraspLift- or StackCube-IRB120-v1"""
    episodes: int = 3
    seed: int = 0
    out_dir: Path = Path("outputs")
    size: int = 256
    """overview video resolution (the hand camera is upscaled to match)"""


def frame(img) -> np.ndarray:
    img = img.cpu().numpy() if isinstance(img, torch.Tensor) else np.asarray(img)
    return img[0] if img.ndim == 4 else img


def upscale(img: np.ndarray, size: int) -> np.ndarray:
    k = -(-size // img.shape[0])
    return np.kron(img, np.ones((k, k, 1), dtype=np.uint8))[:size, :size]


class StepTimer(gym.Wrapper):
    """Times ``env.step`` alone (the overview video's rendering happens outside it)."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.times: list[float] = []

    def step(self, action):
        t0 = time.perf_counter()
        out = self.env.step(action)
        self.times.append(time.perf_counter() - t0)
        return out


def main(args: Args) -> dict:
    check_env_id(args.env_id)
    check_count("--episodes", args.episodes)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    env = StepTimer(
        gym.make(
            args.env_id,
            obs_mode="rgbd",
            render_mode="rgb_array",
            human_render_camera_configs=dict(width=args.size, height=args.size),
        )
    )
    expert = expert_for(env)
    stem = args.env_id.split("-")[0].lower()
    video = args.out_dir / f"{stem}_expert.mp4"
    scene_png = args.out_dir / f"{stem}_scene.png"
    hand_png = args.out_dir / "hand_camera.png"
    episodes = []
    with imageio.get_writer(video, fps=20, macro_block_size=1) as writer:

        def write_frame(_action, result):
            hand = frame(result[0]["sensor_data"]["hand_camera"]["rgb"])
            overview = frame(env.render())
            if not scene_png.exists():
                imageio.imwrite(scene_png, overview)
                imageio.imwrite(hand_png, upscale(hand, 252))
            writer.append_data(np.concatenate([overview, upscale(hand, args.size)], axis=1))

        for f in (scene_png, hand_png):
            f.unlink(missing_ok=True)
        for ep in range(args.episodes):
            episodes.append(run_episode(env, expert, args.seed + ep, on_step=write_frame))
    env.close()
    successes, steps, step_times = sum(e.success for e in episodes), [e.steps for e in episodes], env.times
    result = dict(
        success_rate=successes / args.episodes,
        episodes=args.episodes,
        mean_steps=float(np.mean(steps)),
        step_ms=1000 * float(np.mean(step_times)),
        steps_per_s=1 / float(np.mean(step_times)),
    )
    print(f"scene:  {scene_png.resolve()}")
    print(f"video ({args.episodes} expert episodes, overview | hand camera): {video.resolve()}")
    print(f"success rate {successes}/{args.episodes}, mean {result['mean_steps']:.0f} steps per episode")
    print(
        f"env.step with the 84x84 RGB-D hand camera (rgbd obs, CPU, one process): "
        f"{result['step_ms']:.1f} ms = {result['steps_per_s']:.0f} steps/s (overview video rendering excluded)"
    )
    return result


if __name__ == "__main__":
    with usage_errors(Path(__file__).name):  # a wrong env id or count: one line, exit status 2
        main(parse_flags(Args, Path(__file__).name))
