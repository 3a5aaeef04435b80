"""The PPO actor-critic (``agents.ppo`` trains it): a shared encoder, a Gaussian policy head with a
state-independent log-std, a value head; optionally a frozen deterministic base policy under a residual."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn
from torch.distributions.normal import Normal

from maniskill_irb120.policies.nets import DeterministicActor, NatureCNN, layer_init


class Agent(nn.Module):
    """Shared encoder, separate policy and value heads, state-independent log-std; with ``residual`` the mean is a
    frozen base policy's action plus the actor head's output (a zero-initialised residual)."""

    def __init__(self, image_shape, state_dim: int, action_dim: int, residual: bool = False, init_logstd: float = -0.5):
        super().__init__()
        self.image_shape, self.state_dim, self.action_dim = image_shape, state_dim, action_dim
        self.init_logstd = init_logstd
        self.base = DeterministicActor(image_shape, state_dim, action_dim).requires_grad_(False) if residual else None
        self.encoder = NatureCNN(image_shape, state_dim)
        d = self.encoder.out_dim
        self.critic = nn.Sequential(layer_init(nn.Linear(d, 512)), nn.ReLU(), layer_init(nn.Linear(512, 1)))
        self.actor_mean = nn.Sequential(
            layer_init(nn.Linear(d, 512)), nn.ReLU(), layer_init(nn.Linear(512, action_dim), std=0.01 * np.sqrt(2))
        )
        if residual:
            nn.init.zeros_(self.actor_mean[-1].weight)
            nn.init.zeros_(self.actor_mean[-1].bias)
        self.actor_logstd = nn.Parameter(torch.full((1, action_dim), float(init_logstd)))

    def signature(self) -> dict:
        return dict(
            image_shape=list(self.image_shape) if self.image_shape else None,
            state_dim=self.state_dim,
            action_dim=self.action_dim,
            residual=self.base is not None,
        )

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

    def get_value(self, obs) -> torch.Tensor:
        return self.critic(self.encoder(obs))

    def get_action(self, obs, deterministic: bool = False) -> torch.Tensor:
        mean = self.mean(obs, self.encoder(obs))
        if deterministic:
            return mean
        return Normal(mean, self.actor_logstd.expand_as(mean).exp()).sample()

    def get_action_and_value(self, obs, action=None, with_mean: bool = False):
        x = self.encoder(obs)
        mean = self.mean(obs, x)
        dist = Normal(mean, self.actor_logstd.expand_as(mean).exp())
        if action is None:
            action = dist.sample()
        out = (action, dist.log_prob(action).sum(1), dist.entropy().sum(1), self.critic(x))
        return (*out, mean) if with_mean else out
