"""Demo: the IRB 120 rendered at rest, a scripted tool-frame motion filmed from an overview camera
and from the hand camera (side by side), written to ``outputs/``.

    .venv/bin/python examples/demo.py [--out-dir outputs] [--steps 60]
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import imageio.v2 as imageio
import mani_skill.envs  # noqa: F401
import numpy as np
import sapien
import torch
import tyro
from mani_skill.utils import sapien_utils

import maniskill_irb120  # noqa: F401


@dataclass
class Args:
    out_dir: Path = Path("outputs")
    steps: int = 60
    """control steps of the scripted motion (20 Hz)"""
    size: int = 256
    """overview video resolution"""


def to_uint8(img) -> np.ndarray:
    img = img.cpu().numpy() if isinstance(img, torch.Tensor) else np.asarray(img)
    return img[0] if img.ndim == 4 else img


def scripted_action(t: int) -> np.ndarray:
    """Square in the tool frame with a twist, then descend, close, rise, open: exercises every action."""
    phase = (t // 10) % 6
    a = np.zeros(5, dtype=np.float32)
    a[4] = 1.0
    if phase < 4:
        a[1:3] = [(1, 0), (0, 1), (-1, 0), (0, -1)][phase]
        a[3] = 0.5 if phase % 2 == 0 else -0.5
    elif phase == 4:
        a[0], a[4] = 1.0, -1.0
    else:
        a[0], a[4] = -1.0, 1.0
    return a


def main(args: Args) -> None:
    args.out_dir.mkdir(parents=True, exist_ok=True)
    pose = sapien_utils.look_at([1.0, -0.9, 0.8], [0.25, 0.0, 0.25])
    env = gym.make("Empty-v1", robot_uids="irb120_metalwork", obs_mode="rgbd", render_mode="rgb_array",
                   control_mode="pd_ee_delta_tool",
                   human_render_camera_configs=dict(width=args.size, height=args.size, pose=pose, fov=0.9))
    env.reset(seed=0)
    agent = env.unwrapped.agent
    agent.robot.set_qpos(torch.as_tensor(agent.keyframes["rest"].qpos, dtype=torch.float32)[None])
    agent.controller.reset()
    obs, *_ = env.step(np.array([0, 0, 0, 0, 1], dtype=np.float32))
    rest_png = args.out_dir / "irb120_rest.png"
    imageio.imwrite(rest_png, to_uint8(env.render()))

    video = args.out_dir / "irb120_motion.mp4"
    start = agent.tcp_pose.p[0].numpy().copy()
    step_times = []
    with imageio.get_writer(video, fps=20, macro_block_size=1) as writer:
        for t in range(args.steps):
            t0 = time.perf_counter()
            obs, *_ = env.step(scripted_action(t))
            step_times.append(time.perf_counter() - t0)
            hand = to_uint8(obs["sensor_data"]["hand_camera"]["rgb"])
            hand = np.kron(hand, np.ones((args.size // hand.shape[0] + 1,) * 2 + (1,), dtype=np.uint8))[: args.size, : args.size]
            writer.append_data(np.concatenate([to_uint8(env.render()), hand], axis=1))
    end = agent.tcp_pose.p[0].numpy()
    print(f"rest image:  {rest_png.resolve()}")
    print(f"motion video ({args.steps} steps, overview | hand camera): {video.resolve()}")
    print(f"TCP moved from {np.round(start, 3).tolist()} to {np.round(end, 3).tolist()} m (robot base frame)")
    print(f"env step incl. 84x84 RGB-D hand camera: {1000 * np.mean(step_times):.1f} ms "
          f"({1 / np.mean(step_times):.0f} steps/s, CPU, one process)")
    env.close()


if __name__ == "__main__":
    main(tyro.cli(Args))
