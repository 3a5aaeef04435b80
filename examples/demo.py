"""Demo: the scripted expert clears the table on CPU; one mp4 shows the overview camera beside the
84x84 hand camera, a PNG shows the scene, and the success rate and step timing are printed.

    .venv/bin/python examples/demo.py [--episodes 3] [--seed 0] [--out-dir outputs]
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import imageio.v2 as imageio
import numpy as np
import torch
import tyro

import maniskill_irb120  # noqa: F401
from maniskill_irb120.expert import ENV_ID, TableClearingExpert


@dataclass
class Args:
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


def main(args: Args) -> dict:
    args.out_dir.mkdir(parents=True, exist_ok=True)
    env = gym.make(ENV_ID, obs_mode="rgbd", render_mode="rgb_array",
                   human_render_camera_configs=dict(width=args.size, height=args.size))
    expert = TableClearingExpert(env.unwrapped)
    video = args.out_dir / "table_clearing_expert.mp4"
    scene_png = args.out_dir / "table_clearing_scene.png"
    hand_png = args.out_dir / "hand_camera.png"
    successes, steps, step_times = 0, [], []
    with imageio.get_writer(video, fps=20, macro_block_size=1) as writer:
        for ep in range(args.episodes):
            obs, _ = env.reset(seed=args.seed + ep)
            expert.reset()
            if ep == 0:
                imageio.imwrite(scene_png, frame(env.render()))
                imageio.imwrite(hand_png, upscale(frame(obs["sensor_data"]["hand_camera"]["rgb"]), 252))
            for t in range(1000):
                action = expert.act()
                t0 = time.perf_counter()
                obs, _, term, trunc, info = env.step(action)
                step_times.append(time.perf_counter() - t0)
                hand = upscale(frame(obs["sensor_data"]["hand_camera"]["rgb"]), args.size)
                writer.append_data(np.concatenate([frame(env.render()), hand], axis=1))
                if bool(term[0]) or bool(trunc[0]):
                    break
            successes += bool(info["success"][0])
            steps.append(t + 1)
    env.close()
    result = dict(success_rate=successes / args.episodes, episodes=args.episodes, mean_steps=float(np.mean(steps)),
                  step_ms=1000 * float(np.mean(step_times)), steps_per_s=1 / float(np.mean(step_times)))
    print(f"scene:  {scene_png.resolve()}")
    print(f"video ({args.episodes} expert episodes, overview | hand camera): {video.resolve()}")
    print(f"success rate {successes}/{args.episodes}, mean {result['mean_steps']:.0f} steps per episode")
    print(f"env.step with the 84x84 RGB-D hand camera (rgbd obs, CPU, one process): "
          f"{result['step_ms']:.1f} ms = {result['steps_per_s']:.0f} steps/s (overview video rendering excluded)")
    return result


if __name__ == "__main__":
    main(tyro.cli(Args))
