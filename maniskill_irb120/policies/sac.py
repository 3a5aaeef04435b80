"""The SAC model (``agents.sac`` trains it): LayerNorm double-Q critics over one encoder, a tanh-squashed
Gaussian actor on the critic's features, and optionally IBRL's frozen reference (the cloned policy); it acts
with the better of the actor's and the reference's action by the critic's value."""

from __future__ import annotations

import copy

import numpy as np
import torch
import torch.nn as nn

from maniskill_irb120.policies.nets import NatureCNN, StateNorm

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0


class Critic(nn.Module):
    """Two LayerNorm Q-heads over one encoder (the encoder learns from the critic loss only, as in DrQ)."""

    def __init__(self, image_shape, state_dim: int, action_dim: int, hidden: int = 256):
        super().__init__()
        self.norm = StateNorm(state_dim)
        self.encoder = NatureCNN(image_shape, state_dim)

        def head() -> nn.Sequential:
            return nn.Sequential(
                nn.Linear(self.encoder.out_dim + action_dim, hidden),
                nn.LayerNorm(hidden),
                nn.ReLU(),
                nn.Linear(hidden, hidden),
                nn.LayerNorm(hidden),
                nn.ReLU(),
                nn.Linear(hidden, 1),
            )

        self.q1, self.q2 = head(), head()

    def features(self, obs: dict) -> torch.Tensor:
        return self.encoder(self.norm(obs))

    def forward(self, feats: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([feats, action], dim=1)
        return self.q1(x).squeeze(1), self.q2(x).squeeze(1)


class Actor(nn.Module):
    """Tanh-squashed Gaussian over the critic's (detached) features."""

    def __init__(self, feature_dim: int, action_dim: int, hidden: int = 256):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(feature_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU())
        self.mean = nn.Linear(hidden, action_dim)
        self.log_std = nn.Linear(hidden, action_dim)

    def gaussian(self, feats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, log std) before the tanh."""
        h = self.net(feats)
        return self.mean(h), self.log_std(h).clamp(LOG_STD_MIN, LOG_STD_MAX)

    def forward(self, feats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(sampled action, its log-probability, the deterministic action)."""
        mean, log_std = self.gaussian(feats)
        normal = torch.distributions.Normal(mean, log_std.exp())
        u = normal.rsample()
        a = torch.tanh(u)
        logp = (normal.log_prob(u) - torch.log(1 - a.pow(2) + 1e-6)).sum(1)
        return a, logp, torch.tanh(mean)


class Reference(nn.Module):
    """The cloned policy, frozen (IBRL), with its own copy of the encoder the critic goes on training."""

    def __init__(self, critic: Critic, actor: Actor):
        super().__init__()
        self.norm, self.encoder, self.actor = (
            copy.deepcopy(m).requires_grad_(False) for m in (critic.norm, critic.encoder, actor)
        )

    def forward(self, obs: dict) -> torch.Tensor:
        return self.actor(self.encoder(self.norm(obs)))[2]


class SAC(nn.Module):
    def __init__(self, image_shape, state_dim: int, action_dim: int, init_alpha: float, reference: bool = False):
        super().__init__()
        self.image_shape, self.state_dim, self.action_dim = image_shape, state_dim, action_dim
        self.critic = Critic(image_shape, state_dim, action_dim)
        self.target = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor = Actor(self.critic.encoder.out_dim, action_dim)
        self.log_alpha = nn.Parameter(torch.tensor(float(np.log(init_alpha))))
        self.reference = Reference(self.critic, self.actor) if reference else None

    def freeze_reference(self) -> None:
        """Keep the actor as cloned so far as IBRL's reference policy."""
        self.reference = Reference(self.critic, self.actor)

    def signature(self) -> dict:
        shape = list(self.image_shape) if self.image_shape else None
        return dict(
            image_shape=shape,
            state_dim=self.state_dim,
            action_dim=self.action_dim,
            reference=self.reference is not None,
        )

    def better(self, critic: Critic, feats: torch.Tensor, a: torch.Tensor, b: torch.Tensor):
        """Per sample, whichever of ``a`` and ``b`` ``critic`` values higher (clipped double Q), and its value."""
        qa, qb = torch.min(*critic(feats, a)), torch.min(*critic(feats, b))
        return torch.where((qb > qa)[:, None], b, a), torch.max(qa, qb)

    def act(self, obs: dict, deterministic: bool, noise: float = 0.0) -> torch.Tensor:
        """The actor's action or, with a reference, the better of it and the clone's (``noise``: std of the
        Gaussian on the clone's arm actions when exploring)."""
        with torch.no_grad():
            feats = self.critic.features(obs)
            a, _, mean = self.actor(feats)
            a = mean if deterministic else a
            if self.reference is None:
                return a
            ref = self.reference(obs)
            if not deterministic and noise > 0:
                ref[:, :4] = (ref[:, :4] + noise * torch.randn_like(ref[:, :4])).clamp(-1, 1)
            return self.better(self.critic, feats, a, ref)[0]
