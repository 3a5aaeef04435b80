"""skrl on the tasks: skrl's own ManiSkill wrapper over either backend, and the models for its agents.

    from maniskill_irb120.integrations.skrl import make_skrl_env, policy_and_value

    env = make_skrl_env("GraspLift-IRB120-v1", num_envs=2, obs="state")  # or obs="rgbd"
    models = policy_and_value(env)                                       # {"policy": ..., "value": ...}
    # then skrl's PPO(models=models, memory=RandomMemory(...), ...) and SequentialTrainer, as examples/skrl_ppo.py

:class:`IRB120SkrlWrapper` is skrl's ``ManiSkillWrapper`` (its spaces, seeding, ``reset``, ``render`` and
``close`` as they are) over :func:`~maniskill_irb120.integrations.observations.make_vector_env`: ``backend="cpu"``
(worker processes) or ``"gpu"`` (``physx_cuda``; unverified here: it needs a GPU and a CUDA PhysX). What its
``step`` does differently, and why:

- resets: skrl's wrapper resets ended envs itself after the step (a partial reset through ``env_idx``); our vector
  env already did, in the same step, so a second reset would start yet another episode and throw the first reset's
  away. Here the step's observation is the new episodes' first one, and the ended episodes' last observation is
  kept in ``info["final_observation"]`` (flattened like every observation skrl sees).
- actions: clipped to the action space here, not in the policy (:class:`Policy` says why); a NaN still reaches the
  vector env, which refuses it.
- episode statistics: skrl's trainers log the scalar entries of ``info["episode"]`` (``TrainerCfg.environment_info``)
  each step, and its agents log ``Episode / Total timesteps`` and ``Reward / Total reward`` from the flags
  themselves. So on a step where episodes end, ``info["episode"]`` holds ``"Episode / Success rate (mean)"`` of
  those episodes (the task's ``success`` on their last step); otherwise it is empty (the vector env's per-env
  metrics would be logged as numbers only with one env). skrl averages those per-step means over its write interval,
  which weighs a step where two episodes ended like one where one did; ``recent_success`` keeps each ended
  episode's own success (the last 100), what a progress line reads.

skrl flattens a Dict observation into one float vector (sorted keys); :func:`policy_and_value`'s models undo it
with skrl's ``unflatten_tensorized_space`` and read the image through a CNN.

skrl's Gaussian clips its sample rather than squashing it, which SAC cannot use (:class:`TanhSquashed` says why):
the SAC configs name ``SquashedGaussianMixin``, and :func:`make_runner` is skrl's ``Runner`` that knows it.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Optional

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn

from maniskill_irb120.integrations.observations import (
    CONTROL_MODE,
    IMAGE_KEY,
    STATE_KEY,
    StepThreads,
    learner_threads_for,
    wrapped_vector_env,
)
from maniskill_irb120.integrations.selection import ValidationSelection

try:
    from skrl.envs.wrappers.torch.mani_skill_envs import ManiSkillWrapper
    from skrl.models.torch import DeterministicMixin, GaussianMixin, Model
    from skrl.utils.spaces.torch import flatten_tensorized_space, tensorize_space, unflatten_tensorized_space
except ModuleNotFoundError as e:  # pragma: no cover - the extra is missing
    if e.name is None or not e.name.startswith("skrl"):
        raise
    message = "maniskill_irb120.integrations.skrl needs skrl: pip install -e '.[skrl]'"
    raise ModuleNotFoundError(message, name=e.name) from e

SUCCESS_KEY = "Episode / Success rate (mean)"


class IRB120SkrlWrapper(ManiSkillWrapper):
    """skrl's ManiSkill wrapper over an auto-resetting batched env from ``make_vector_env`` (see the module doc).
    ``seed``: the first reset's (env i gets ``seed + i`` on the CPU); None leaves it to skrl (``config.torch.key``).
    ``learner_threads``: torch's threads between CPU worker steps (``observations.StepThreads``)."""

    def __init__(self, env: gym.vector.VectorEnv, seed: Optional[int] = None, learner_threads: int = 1):
        self._threads = StepThreads(env, learner_threads)
        super().__init__(env)
        if seed is not None:
            self._seed = int(seed)
        space = self.action_space
        box = isinstance(space, gym.spaces.Box)
        self._bounds = tuple(torch.as_tensor(b, device=self.device) for b in (space.low, space.high)) if box else None
        self.recent_success: deque[bool] = deque(maxlen=100)  # each ended episode's own success, latest last

    def reset(self) -> tuple[torch.Tensor, Any]:
        with self._threads.stepping():
            return super().reset()

    def _flat(self, obs: Any) -> torch.Tensor:
        return flatten_tensorized_space(tensorize_space(self.observation_space, obs, device=self.device))

    def step(self, actions: torch.Tensor):
        actions = unflatten_tensorized_space(self.action_space, actions)
        if self._bounds is not None:  # the policy's sample, clipped here only (see Policy)
            low, high = (b.to(actions.device) for b in self._bounds)
            actions = torch.maximum(torch.minimum(actions, high), low)  # NaN passes through, for the env to refuse
        with torch.no_grad(), self._threads.stepping():
            obs, reward, terminated, truncated, info = self._env.step(actions)
        info = {k: v for k, v in info.items() if k != "episode"}
        dones = (terminated | truncated).flatten()
        episode: dict[str, torch.Tensor] = {}
        if dones.any():
            success = info["final_info"].get("success")
            if isinstance(success, torch.Tensor):
                episode[SUCCESS_KEY] = success[dones].float().mean()
                self.recent_success.extend(success[dones].cpu().tolist())
            info["final_observation"] = self._flat(info["final_observation"])
        info["episode"] = episode
        self._info = info
        self._observations = self._flat(obs)
        device = self.device
        return (
            self._observations.to(device),
            reward.to(device).float().view(-1, 1),
            terminated.to(device).view(-1, 1),
            truncated.to(device).view(-1, 1),
            info,
        )


def make_skrl_env(
    env_id: str,
    num_envs: int = 2,
    obs: str = "state",
    *,
    backend: str = "auto",
    reward_mode: Optional[str] = None,
    control_mode: Optional[str] = CONTROL_MODE,
    seed: Optional[int] = None,
    wrappers: Sequence[Callable[[gym.Env], gym.Env]] = (),
    env_kwargs: Optional[dict] = None,
    learner_threads: Optional[int] = None,
) -> IRB120SkrlWrapper:
    """``num_envs`` envs of ``env_id`` for skrl, giving ``obs`` (``"state"`` or ``"rgbd"``: image + state, flattened
    by skrl), with ``reward_mode`` and ``control_mode`` passed to the task (default: its ``normalized_dense`` reward,
    the tool-frame action). ``backend``: ``"cpu"``, ``"gpu"`` or ``"auto"`` (the GPU when CUDA is there).
    ``learner_threads``: torch's threads between CPU worker steps (default 1 from state, the package's torch threads
    from the camera; one while the envs step: ``observations.StepThreads``)."""
    threads = learner_threads_for(obs, learner_threads)
    return wrapped_vector_env(
        lambda venv: IRB120SkrlWrapper(venv, seed=seed, learner_threads=threads),
        env_id,
        num_envs,
        obs,
        backend=backend,
        reward_mode=reward_mode,
        control_mode=control_mode,
        wrappers=wrappers,
        env_kwargs=env_kwargs,
    )


# ---------------------------------------------------------------------------- models
class Encoder(nn.Module):
    """skrl's flat observation -> features: an MLP on the state vector; with an image, the Nature DQN CNN (SB3's
    ``NatureCNN``: 32 8x8/4, 64 4x4/2, 64 3x3/1, then 256 units) on it, its features beside the state's."""

    def __init__(self, observation_space: gym.Space, hidden: int = 256):
        super().__init__()
        self.space = observation_space
        self.image = isinstance(observation_space, gym.spaces.Dict)
        if self.image:
            c, h, w = observation_space[IMAGE_KEY].shape
            self.cnn = nn.Sequential(
                nn.Conv2d(c, 32, 8, stride=4), nn.ReLU(),
                nn.Conv2d(32, 64, 4, stride=2), nn.ReLU(),
                nn.Conv2d(64, 64, 3, stride=1), nn.ReLU(),
                nn.Flatten(),
            )  # fmt: skip
            with torch.no_grad():
                n = self.cnn(torch.zeros(1, c, h, w)).shape[1]
            self.cnn_head = nn.Sequential(nn.Linear(n, hidden), nn.ReLU())
            state_dim = observation_space[STATE_KEY].shape[0]
        else:
            state_dim = observation_space.shape[0]
        self.mlp = nn.Sequential(nn.Linear(state_dim, hidden), nn.ELU(), nn.Linear(hidden, hidden), nn.ELU())
        self.out_dim = hidden * (2 if self.image else 1)

    def forward(self, flat: torch.Tensor) -> torch.Tensor:
        if not self.image:
            return self.mlp(flat)
        obs = unflatten_tensorized_space(self.space, flat)
        img = self.cnn_head(self.cnn(obs[IMAGE_KEY].float() / 255.0))
        return torch.cat([img, self.mlp(obs[STATE_KEY])], dim=1)


class Policy(GaussianMixin, Model):
    """A Gaussian policy: the mean from :class:`Encoder`'s features, a state-independent log std (skrl's examples'
    layout). Its actions are not clipped (``clip_actions=False``, as Isaac Lab's skrl PPO configurations have it):
    skrl's mixin scores the clipped action's log-probability, so once the mean leaves [-1, 1] the stored
    log-probabilities fall thousands below zero, PPO's ratio overflows to inf and one update writes NaN into every
    weight. :class:`IRB120SkrlWrapper` clips what reaches the env, as SB3 does, and skrl's memory keeps the sample."""

    def __init__(self, observation_space, action_space, device, init_log_std: float = 0.0):
        Model.__init__(self, observation_space=observation_space, action_space=action_space, device=device)
        GaussianMixin.__init__(self, clip_actions=False, clip_log_std=True, min_log_std=-20, max_log_std=2)
        self.encoder = Encoder(observation_space)
        self.mean = nn.Linear(self.encoder.out_dim, self.num_actions)
        self.log_std = nn.Parameter(torch.full((self.num_actions,), float(init_log_std)))

    def compute(self, inputs, role=""):
        return self.mean(self.encoder(inputs["observations"])), {"log_std": self.log_std}


class Value(DeterministicMixin, Model):
    """A state-value network on its own :class:`Encoder` (actor and critic share nothing, as in skrl's examples)."""

    def __init__(self, observation_space, action_space, device):
        Model.__init__(self, observation_space=observation_space, action_space=action_space, device=device)
        DeterministicMixin.__init__(self, clip_actions=False)
        self.encoder = Encoder(observation_space)
        self.head = nn.Linear(self.encoder.out_dim, 1)

    def compute(self, inputs, role=""):
        return self.head(self.encoder(inputs["observations"])), {}


def policy_and_value(env: IRB120SkrlWrapper, device: Optional[torch.device] = None) -> dict[str, Model]:
    """``{"policy": Policy, "value": Value}`` for skrl's PPO (or any agent with those roles) on ``env``'s spaces."""
    device = device or env.device
    return {
        "policy": Policy(env.observation_space, env.action_space, device),
        "value": Value(env.observation_space, env.action_space, device),
    }


class TanhSquashed:
    """A Gaussian whose sample goes through a tanh, scored by the change of variables: what SB3's, ManiSkill's and
    CleanRL's SAC sample from, and what skrl's ``GaussianMixin`` lacks (it clips the sample, ``clip_actions``, and
    scores the clipped action as the Gaussian's). SAC maximises the entropy it is given, and a clipped Gaussian's
    grows with σ without end while the clipped actions stay the same, so its log std runs to its clamp (the skrl SAC
    probe ``skrl_sac_clipped_sample``: σ 7.4, nine actions in ten at a bound). A squashed Gaussian's entropy falls as
    σ grows past ~1 (the mass piles at ±1 with an infinite density there), so its temperature controls it. Mixed
    into a model of skrl's ``gaussian_model`` by :func:`squashed_gaussian_model`; its mean is pre-tanh, and
    ``mean_actions`` is its tanh, what plays deterministically."""

    def act(self, inputs: dict[str, Any], *, role: str = "") -> tuple[torch.Tensor, dict[str, Any]]:
        mean, outputs = self.compute(inputs, role)
        log_std = outputs["log_std"]
        if self._g_clip_log_std:
            log_std = torch.clamp(log_std, min=self._g_min_log_std, max=self._g_max_log_std)
        outputs["log_std"] = log_std
        self._g_distribution = torch.distributions.Normal(mean, log_std.exp())
        taken = inputs.get("taken_actions")
        if taken is None:
            pre = self._g_distribution.rsample()
            actions = torch.tanh(pre)
        else:  # a stored action's pre-image; the bound itself has none, so it is read just inside
            actions = taken
            pre = torch.atanh(taken.clamp(-1.0 + 1e-6, 1.0 - 1e-6))
        # log(1 - tanh(x)^2) = 2 (log 2 - x - softplus(-2x)): exact where tanh(x) rounds to ±1 (SpinningUp's form)
        log_det = 2.0 * (np.log(2.0) - pre - torch.nn.functional.softplus(-2.0 * pre))
        outputs["log_prob"] = (self._g_distribution.log_prob(pre) - log_det).sum(dim=-1, keepdim=True)
        outputs["mean_actions"] = torch.tanh(mean)
        return actions, outputs


def squashed_gaussian_model(*, action_space: gym.Space, **kwargs: Any) -> Model:
    """skrl's ``gaussian_model`` (its network, log std and clamps, from the same YAML keys) sampling through a tanh
    (:class:`TanhSquashed`): the ``SquashedGaussianMixin`` class of a model in the YAML, which :func:`make_runner`
    knows. The action space must be [-1, 1], which the tanh covers; ``clip_actions`` (a second bound on a bounded
    sample) and a ``reduction`` other than the sum (the actions' joint density) are refused by name."""
    from skrl.utils.model_instantiators.torch import gaussian_model

    low, high = np.asarray(action_space.low), np.asarray(action_space.high)
    if not (np.all(low == -1.0) and np.all(high == 1.0)):
        raise ValueError(f"SquashedGaussianMixin samples in [-1, 1]; this action space is [{low.min()}, {high.max()}]")
    if kwargs.get("clip_actions"):
        raise ValueError("SquashedGaussianMixin: clip_actions must be False (the tanh bounds the sample already)")
    if kwargs.get("reduction", "sum") != "sum":
        raise ValueError(f"SquashedGaussianMixin: reduction {kwargs['reduction']!r}; the sample's density is the sum")
    if kwargs.get("return_source"):
        return gaussian_model(action_space=action_space, **kwargs)
    model = gaussian_model(action_space=action_space, **dict(kwargs, clip_actions=False))
    model.__class__ = type("SquashedGaussianModel", (TanhSquashed, type(model)), {})
    return model


def make_runner(env: Any, cfg: dict) -> Any:
    """skrl's own ``Runner`` on ``cfg`` (the YAML's form, as Isaac Lab runs it), knowing one model class more:
    ``SquashedGaussianMixin`` (:func:`squashed_gaussian_model`), for SAC."""
    from skrl.utils.runner.torch import Runner

    class _Runner(Runner):
        def _component(self, name: str) -> Any:
            if name.lower() == "squashedgaussianmixin":
                return squashed_gaussian_model
            return super()._component(name)

    return _Runner(env, cfg)


# ---------------------------------------------------------------------------- deploying and selecting
def deterministic_action(agent: Any, observation_space: gym.Space, obs: Any) -> torch.Tensor:
    """``agent``'s deterministic action, (n, actions): its Gaussian's mean (a squashed one's tanh), clipped to [-1, 1]
    as the adapter clips what reaches the env, for an adapter observation (``make_single_env``'s, unbatched, or a
    batch of them; numpy or torch), flattened as skrl flattens it and scaled by the agent's own observation scaler
    (without updating it)."""
    with torch.no_grad():
        _, out = agent.policy.act({"observations": _scaled_observations(agent, observation_space, obs)}, role="policy")
    return out["mean_actions"].clamp(-1, 1)


def deterministic_value(agent: Any, observation_space: gym.Space, obs: Any) -> torch.Tensor:
    """``agent``'s critic ``V(s)``, (n,), in return units: the observation prepared as :func:`deterministic_action`
    prepares it, the value unscaled by the agent's value preprocessor (PPO's ``value_preprocessor``, which the
    critic's output is trained against) when it has one."""
    with torch.no_grad():
        v, _ = agent.value.act({"observations": _scaled_observations(agent, observation_space, obs)}, role="value")
        unscale = getattr(agent, "_value_preprocessor", None)
        v = unscale(v, inverse=True) if unscale is not None else v
    return v.reshape(-1)


def _scaled_observations(agent: Any, observation_space: gym.Space, obs: Any) -> torch.Tensor:
    """An adapter observation (one or a batch; numpy or torch) flattened as skrl flattens it and scaled by the
    agent's own observation preprocessor, without updating its statistics."""
    preprocess = getattr(agent, "_observation_preprocessor", None) or (lambda o: o)
    flat = flatten_tensorized_space(tensorize_space(observation_space, obs, device=agent.device))
    return preprocess(flat.float())


def deterministic_policy(agent: Any, observation_space: gym.Space) -> Callable[[Any], np.ndarray]:
    """:func:`deterministic_action` for one unbatched observation, as a numpy action: what ``held_out_success`` and
    the other one-env episode loops play."""

    def act(obs: Any) -> np.ndarray:
        return deterministic_action(agent, observation_space, obs)[0].cpu().numpy()

    return act


class SelectOnValidation(ValidationSelection):
    """Checkpoint selection for skrl (``integrations.selection`` says why and how): every ``every`` env steps the
    deterministic policy plays ``episodes`` validation episodes, and the best so far by success is kept in
    ``save_path`` as ``best_agent.pt`` (``agent.save``: its models and observation scaler; ``agent.load`` deploys it)
    with ``best.json``. skrl's runner keeps the best mean training reward instead, which on these tasks prefers
    holding the object to succeeding. A ``callback:`` entry of the project's skrl YAML (``agents/configs/loader.py``
    builds it), or from code: ``SelectOnValidation(every=12500).attach(agent, env, "GraspLift-IRB120-v1")`` before
    ``trainer.train()``."""

    def attach(self, agent: Any, env: IRB120SkrlWrapper, env_id: str, obs: str = "state", env_steps: int = 0) -> None:
        """Check ``agent`` as it trains on ``env``: around its ``post_interaction``, which skrl's trainers call after
        every vector step of ``env.num_envs`` env steps. ``env_steps``: those already trained (a resumed run's; skrl
        counts its timesteps from 0 in every session). ``obs``: what ``env`` gives (``"state"`` or ``"rgbd"``)."""
        if obs not in ("state", "rgbd"):
            raise ValueError(f"SelectOnValidation.attach: obs must be 'state' or 'rgbd', not {obs!r}")
        self.start(env_steps)
        post, per_step, act = agent.post_interaction, env.num_envs, deterministic_policy(agent, env.observation_space)

        def save(folder: Path) -> None:
            agent.save(str(folder / "best_agent.pt"))

        def post_interaction(*, timestep: int, timesteps: int) -> None:
            post(timestep=timestep, timesteps=timesteps)  # the agent's own: its update, when a rollout is full
            steps = env_steps + (timestep + 1) * per_step
            if self.due(steps):
                rate, _ = self.validate(steps, act, env_id, obs, save)
                agent.track_data("Eval / Validation success", rate)

        agent.post_interaction = post_interaction


def is_off_policy(agent: Any) -> bool:
    """Whether ``agent`` learns from a replay memory (skrl's off-policy configs have ``learning_starts``; its
    on-policy ones a rollout memory that a resumed run collects again)."""
    return hasattr(agent.cfg, "learning_starts")


def off_policy_state(agent: Any) -> dict:
    """What an off-policy skrl agent's run needs to go on as it was and ``agent.save`` leaves out: the replay
    memory's filled rows (skrl saves models, optimisers and scalers only) and SAC's temperature (a tensor, not a
    module: skrl saves its optimiser and not its value). Empty for an on-policy agent (no ``learning_starts``): its
    memory is one rollout, which a resumed run collects again. :func:`restore_off_policy_state` puts it back."""
    if not is_off_policy(agent):
        return {}
    memory = agent.memory
    rows = memory.memory_size if memory.filled else memory.memory_index
    state: dict[str, Any] = dict(
        rows=rows, memory_index=memory.memory_index, env_index=memory.env_index, filled=memory.filled,
        tensors={name: tensor[:rows].clone() for name, tensor in memory.tensors.items()},
    )  # fmt: skip
    if hasattr(agent, "log_entropy_coefficient"):
        state["log_entropy_coefficient"] = agent.log_entropy_coefficient.detach().clone()
    return state


def restore_off_policy_state(agent: Any, state: dict, vector_steps_done: int) -> None:
    """Put :func:`off_policy_state`'s ``state`` back into a freshly built ``agent`` (after ``agent.load``), whose
    run has trained ``vector_steps_done`` vector steps before. skrl's trainers count their timesteps from 0 in every
    session, so the random steps and the learning start left are what remains of them, not all of them again. A
    ``state`` whose memory does not fit the agent's (another config's) raises, naming the difference."""
    if not state:
        return
    memory = agent.memory
    for name, saved in state["tensors"].items():
        own = memory.tensors.get(name)
        if own is None or own.shape[1:] != saved.shape[1:] or saved.shape[0] > own.shape[0]:
            shape = None if own is None else tuple(own.shape)
            raise ValueError(f"restore_off_policy_state: saved memory tensor {name!r} {tuple(saved.shape)} does not "
                             f"fit this agent's memory {shape}")  # fmt: skip
    for name, saved in state["tensors"].items():
        memory.tensors[name][: state["rows"]].copy_(saved)
    memory.memory_index, memory.env_index, memory.filled = state["memory_index"], state["env_index"], state["filled"]
    if "log_entropy_coefficient" in state and hasattr(agent, "log_entropy_coefficient"):
        with torch.no_grad():
            agent.log_entropy_coefficient.copy_(state["log_entropy_coefficient"])
        agent._entropy_coefficient = torch.exp(agent.log_entropy_coefficient.detach())
    agent.cfg.random_timesteps = max(0, agent.cfg.random_timesteps - vector_steps_done)
    agent.cfg.learning_starts = max(0, agent.cfg.learning_starts - vector_steps_done)
