"""The PPO actor-critic (``agents.ppo`` trains it): a shared encoder, a Gaussian policy head with a
state-independent log-std, a value head; optionally a frozen deterministic base policy under a residual.
From state it can instead be ManiSkill's state PPO network (separate 3x256 tanh actor and critic) behind a
running observation normaliser, the pair RL from the reward alone uses. ``logstd="state"`` gives the policy a
log-std that depends on the state (a small head beside the mean): one learned log-std must be small everywhere
for a sampled episode to hold an object still, which also ends the exploration everywhere else.
``critic_obs="privileged"`` makes it an asymmetric actor-critic: the value head reads the privileged state
(``obs["privileged"]``, training envs only) through its own 3x256 tanh MLP and running normaliser, while the actor
reads the camera and proprioception alone, so the policy acts (and deploys) without the privileged state.
``encoder="keypoints"`` puts :class:`~maniskill_irb120.policies.nets.KeypointCNN` (conv + spatial softmax, DAgger's
``--encoder keypoints``) under the heads instead of the Nature CNN."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn
from torch.distributions.normal import Normal

from maniskill_irb120.policies.nets import ENCODERS, DeterministicActor, RunningNorm, camera_encoder, layer_init

STATE_NETS = ("shared", "mlp")
LOGSTDS = ("param", "state")
CRITIC_OBS = ("same", "privileged")
PRIVILEGED = "privileged"
"""the observation key of the privileged state an asymmetric critic reads (agents.common.envs.PrivilegedStateObs)"""
LOGSTD_RANGE = (-5.0, 2.0)
"""bounds of a state-dependent log-std (as SAC's): a head cannot shrink the noise to nothing or blow it up"""


class Agent(nn.Module):
    """Shared encoder, separate policy and value heads, a state-independent log-std (``logstd="state"``: a head on
    the actor's input); with ``residual`` the mean is a frozen base policy's action plus the actor head's output (a
    zero-initialised residual). ``encoder``: the camera encoder under the heads, ``nature`` (NatureCNN),
    ``keypoints`` (KeypointCNN) or ``keypoints-depth`` (with a depth-only stack beside it); a residual's frozen
    base is built with the same one (a DAgger policy of that encoder)."""

    def __init__(
        self,
        image_shape,
        state_dim: int,
        action_dim: int,
        residual: bool = False,
        init_logstd: float = -0.5,
        state_net: str = "shared",
        obs_norm: bool = False,
        logstd: str = "param",
        critic_obs: str = "same",
        privileged_dim: int = 0,
        encoder: str = "nature",
    ):
        super().__init__()
        if encoder not in ENCODERS:
            raise ValueError(f"unknown encoder {encoder!r}; expected one of {ENCODERS}")
        if encoder != "nature" and (image_shape is None or state_net != "shared"):
            raise ValueError(
                f"encoder={encoder!r} reads the camera: it needs an image and state_net='shared' (got "
                f"image_shape={image_shape}, state_net={state_net!r})"
            )
        if state_net not in STATE_NETS:
            raise ValueError(f"unknown state_net {state_net!r}; expected one of {STATE_NETS}")
        if logstd not in LOGSTDS:
            raise ValueError(f"unknown logstd {logstd!r}; expected one of {LOGSTDS}")
        if logstd == "state" and residual:
            raise ValueError("logstd='state' has no residual form: the KL to the base assumes one log-std per action")
        if state_net == "mlp" and (image_shape is not None or residual):
            raise ValueError("state_net='mlp' is ManiSkill's state PPO network: no camera, no residual base")
        if critic_obs not in CRITIC_OBS:
            raise ValueError(f"unknown critic_obs {critic_obs!r}; expected one of {CRITIC_OBS}")
        if critic_obs == "privileged" and (image_shape is None or privileged_dim < 1):
            raise ValueError(
                "critic_obs='privileged' gives a camera policy's critic the privileged state: it needs an image and "
                f"privileged_dim >= 1 (got image_shape={image_shape}, privileged_dim={privileged_dim})"
            )
        self.critic_obs, self.privileged_dim = critic_obs, privileged_dim if critic_obs == "privileged" else 0
        self.image_shape, self.state_dim, self.action_dim = image_shape, state_dim, action_dim
        self.init_logstd, self.state_net, self.logstd, self.encoder_kind = init_logstd, state_net, logstd, encoder
        self.norm = RunningNorm(state_dim) if obs_norm else None
        self.base = (
            DeterministicActor(image_shape, state_dim, action_dim, encoder=encoder).requires_grad_(False)
            if residual
            else None
        )
        if state_net == "mlp":  # ManiSkill's examples/baselines/ppo/ppo.py Agent, sizes and initialisation
            self.encoder = nn.Identity()
            self.critic = nn.Sequential(
                *(m for i in range(3) for m in (layer_init(nn.Linear(state_dim if i == 0 else 256, 256)), nn.Tanh())),
                layer_init(nn.Linear(256, 1)),
            )
            self.actor_mean = nn.Sequential(
                *(m for i in range(3) for m in (layer_init(nn.Linear(state_dim if i == 0 else 256, 256)), nn.Tanh())),
                layer_init(nn.Linear(256, action_dim), std=0.01 * np.sqrt(2)),
            )
        else:
            self.encoder = camera_encoder(encoder, image_shape, state_dim)
            d = self.encoder.out_dim
            self.critic = nn.Sequential(layer_init(nn.Linear(d, 512)), nn.ReLU(), layer_init(nn.Linear(512, 1)))
            self.actor_mean = nn.Sequential(
                layer_init(nn.Linear(d, 512)), nn.ReLU(), layer_init(nn.Linear(512, action_dim), std=0.01 * np.sqrt(2))
            )
        self.critic_norm = None
        if critic_obs == "privileged":  # the state PPO's critic (and its normaliser) on the privileged state
            self.critic_norm = RunningNorm(privileged_dim)
            width = (privileged_dim, 256, 256)
            self.critic = nn.Sequential(
                *(m for w in width for m in (layer_init(nn.Linear(w, 256)), nn.Tanh())), layer_init(nn.Linear(256, 1))
            )
        if residual:
            nn.init.zeros_(self.actor_mean[-1].weight)
            nn.init.zeros_(self.actor_mean[-1].bias)
        if logstd == "state":  # starts as the parameter would: every state at init_logstd
            width = state_dim if state_net == "mlp" else self.encoder.out_dim
            self.actor_logstd_head = nn.Sequential(
                layer_init(nn.Linear(width, 64)),
                nn.Tanh(),
                layer_init(nn.Linear(64, 64)),
                nn.Tanh(),
                nn.Linear(64, action_dim),
            )
            nn.init.zeros_(self.actor_logstd_head[-1].weight)
            nn.init.constant_(self.actor_logstd_head[-1].bias, float(init_logstd))
        else:
            self.actor_logstd = nn.Parameter(torch.full((1, action_dim), float(init_logstd)))

    def features(self, obs, precision: str = "fp32") -> torch.Tensor:
        """What the heads read: the encoder's features, or (``state_net='mlp'``) the normalised state.
        ``precision="bf16"`` runs the encoder (its convolutions, the cost of a camera update) under bf16 autocast
        and hands the heads float32 features, so the log-probabilities, values and everything after them stay
        float32 (the trainer's ``--precision``; agents/common/precision.py says where it pays)."""
        if self.norm is not None:
            obs = self.norm(obs)
        if self.state_net == "mlp":
            return self.encoder(obs["state"].float())
        if precision == "fp32":
            return self.encoder(obs)
        if precision != "bf16":
            raise ValueError(f"precision {precision!r} is not resolved (fp32 or bf16)")
        device = obs["state"].device.type
        with torch.autocast(device_type=device, dtype=torch.bfloat16):
            x = self.encoder(obs)
        return x.float()

    def signature(self) -> dict:
        sig = dict(
            image_shape=list(self.image_shape) if self.image_shape else None,
            state_dim=self.state_dim,
            action_dim=self.action_dim,
            residual=self.base is not None,
            state_net=self.state_net,
            obs_norm=self.norm is not None,
            logstd=self.logstd,
        )
        if self.critic_obs != "same":  # the signature predates the choice: older checkpoints load as they are
            sig.update(critic_obs=self.critic_obs, privileged_dim=self.privileged_dim)
        if self.encoder_kind != "nature":  # likewise: a Nature CNN checkpoint's signature is the one it always had
            sig["encoder"] = self.encoder_kind
        return sig

    def mean(self, obs, x: torch.Tensor) -> torch.Tensor:
        m = self.actor_mean(x)
        return m if self.base is None else m + self.base_action(obs)

    def base_action(self, obs) -> torch.Tensor:
        with torch.no_grad():
            return self.base(obs)

    def kl_to_base(self, obs, mean: torch.Tensor) -> torch.Tensor:
        """KL(N(mean, std) || N(base(obs), exp(init_logstd))) per sample, summed over action dims."""
        ref_logstd = torch.full_like(mean, self.init_logstd)
        logstd = self.actor_logstd.expand_as(mean)
        var, ref_var = (2 * logstd).exp(), (2 * ref_logstd).exp()
        kl = ref_logstd - logstd + (var + (mean - self.base_action(obs)) ** 2) / (2 * ref_var) - 0.5
        return kl.sum(1)

    def log_std(self, x: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
        """(N, action_dim) log-std for the features ``x`` (those the mean was computed from)."""
        if self.logstd == "state":
            return self.actor_logstd_head(x).clamp(*LOGSTD_RANGE)
        return self.actor_logstd.expand_as(mean)

    def value(self, obs, x) -> torch.Tensor:
        """(N, 1) the critic's value: of the features ``x`` (the actor's), or with ``critic_obs="privileged"`` of
        the normalised privileged state (``x`` unused: None will do)."""
        if self.critic_norm is None:
            return self.critic(x)
        if PRIVILEGED not in obs:
            raise KeyError(
                f"critic_obs='privileged': the observation has no {PRIVILEGED!r} key (the training envs add it; the "
                "policy's actions never need it)"
            )
        return self.critic(self.critic_norm({"state": obs[PRIVILEGED]})["state"])

    def get_value(self, obs) -> torch.Tensor:
        return self.value(obs, None if self.critic_norm is not None else self.features(obs))

    def get_action(self, obs, deterministic: bool = False) -> torch.Tensor:
        x = self.features(obs)
        mean = self.mean(obs, x)
        if deterministic:
            return mean
        return Normal(mean, self.log_std(x, mean).exp()).sample()

    def get_action_and_value(self, obs, action=None, with_mean: bool = False, precision: str = "fp32", generator=None):
        """An action (sampled unless given), its log-probability, the entropy and the value; ``precision``: the
        encoder's (:meth:`features`), the heads are float32 either way. ``generator``: a ``torch.Generator`` the
        sample draws from instead of torch's global one (a collector thread beside the learner's, agents.ppo's
        ``--overlap``, so neither moves the other's random numbers)."""
        x = self.features(obs, precision)
        mean = self.mean(obs, x)
        dist = Normal(mean, self.log_std(x, mean).exp())
        if action is None:
            action = dist.sample() if generator is None else torch.normal(mean, dist.stddev, generator=generator)
        out = (action, dist.log_prob(action).sum(1), dist.entropy().sum(1), self.value(obs, x))
        return (*out, mean) if with_mean else out
