"""Replay storage trainers share: :class:`Dataset`, preallocated CPU rows in a ring, is DAgger's aggregated
dataset and SAC's demo and online replay."""

from __future__ import annotations

from typing import Optional

import torch


class Dataset:
    """Aggregated (observation, expert action[, auxiliary target]) rows in preallocated CPU tensors, a ring
    when full."""

    def __init__(self, capacity: int):
        self.capacity, self.size, self.pos = capacity, 0, 0
        self.obs: dict[str, torch.Tensor] = {}
        self.act: Optional[torch.Tensor] = None
        self.aux: Optional[torch.Tensor] = None

    def add(self, obs: dict[str, torch.Tensor], act: torch.Tensor, aux: Optional[torch.Tensor] = None) -> None:
        if self.act is None:
            self.obs = {k: torch.empty((self.capacity,) + v.shape[1:], dtype=v.dtype) for k, v in obs.items()}
            self.act = torch.empty((self.capacity,) + act.shape[1:], dtype=torch.float32)
            if aux is not None:
                self.aux = torch.empty((self.capacity,) + aux.shape[1:], dtype=torch.float32)
        if (aux is None) != (self.aux is None):
            raise ValueError("a dataset's rows either all carry auxiliary targets or none does")
        idx = (self.pos + torch.arange(act.shape[0])) % self.capacity
        for k, v in obs.items():
            self.obs[k][idx] = v.cpu()
        self.act[idx] = act.float().cpu()
        if aux is not None:
            self.aux[idx] = aux.float().cpu()
        self.pos = int(idx[-1] + 1) % self.capacity
        self.size = min(self.size + act.shape[0], self.capacity)

    def sample(self, n: int, device) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """(observations, actions) of ``n`` random rows (a replay's minibatch)."""
        obs, act, _ = self.sample_with_aux(n, device)
        return obs, act

    def sample_with_aux(self, n: int, device) -> tuple[dict[str, torch.Tensor], torch.Tensor, Optional[torch.Tensor]]:
        idx = torch.randint(0, self.size, (n,))
        aux = self.aux[idx].to(device) if self.aux is not None else None
        return {k: v[idx].to(device) for k, v in self.obs.items()}, self.act[idx].to(device), aux

    def state_dict(self) -> dict:
        n = self.size
        return dict(
            capacity=self.capacity,
            pos=self.pos,
            size=n,
            # clones: torch.save writes a view's whole storage, i.e. the empty capacity too
            obs={k: v[:n].clone() for k, v in self.obs.items()},
            act=self.act[:n].clone() if n else None,
            aux=self.aux[:n].clone() if n and self.aux is not None else None,
        )

    def load_state_dict(self, d: dict) -> None:
        self.__init__(d["capacity"])
        if d["size"]:
            self.add(d["obs"], d["act"], d.get("aux"))
            self.pos = d["pos"]
