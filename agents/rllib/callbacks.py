"""Task metrics from RLlib's env runners under the names ``agents.ppo`` logs (``success_rate``,
``grasped_rate``, ``lifted_rate``, ``dropped_rate``, ``collided_rate``, ``return_r_<term>``), so RLlib curves and
ours line up in one TensorBoard."""

from __future__ import annotations

from ray.rllib.callbacks.callbacks import RLlibCallback

from agents.common import EVENT_KEYS, REWARD_TERM_PREFIX

WINDOW = 100
"""episodes each reported rate is averaged over (RLlib's own episode_return_mean uses the same)"""


class TaskMetrics(RLlibCallback):
    """Per episode: did each event ever happen, and each reward term's sum. ``custom_data`` survives RLlib's
    episode chunking, so an episode split across ``sample()`` calls still counts once, in full."""

    def on_episode_step(self, *, episode, **kwargs) -> None:
        info = episode.get_infos(-1)
        data = episode.custom_data
        for k, v in info.items():
            if k in EVENT_KEYS:
                data[f"{k}_rate"] = bool(data.get(f"{k}_rate", False) or bool(v))
            elif k.startswith(REWARD_TERM_PREFIX):
                data[f"return_{k}"] = float(data.get(f"return_{k}", 0.0)) + float(v)

    def on_episode_end(self, *, episode, metrics_logger, **kwargs) -> None:
        for k, v in episode.custom_data.items():
            metrics_logger.log_value(k, float(v), reduce="mean", window=WINDOW)
