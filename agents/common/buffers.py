"""Replay storage trainers share: :class:`Dataset`, preallocated CPU rows in a ring, is DAgger's aggregated
dataset and SAC's demo and online replay. See docs/training.md."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import torch

from agents.common.checkpoints import atomic_save


class Dataset:
    """Aggregated (observation, expert action[, auxiliary target]) rows in preallocated CPU tensors, a ring
    when full."""

    def __init__(self, capacity: int):
        self.capacity, self.size, self.pos = capacity, 0, 0
        self.added = 0  # rows ever added: row g lives in slot g % capacity until overwritten
        self.obs: dict[str, torch.Tensor] = {}
        self.act: Optional[torch.Tensor] = None
        self.aux: Optional[torch.Tensor] = None

    def add(self, obs: dict[str, torch.Tensor], act: torch.Tensor, aux: Optional[torch.Tensor] = None) -> None:
        idx = (self.pos + torch.arange(act.shape[0])) % self.capacity
        self._put(idx, obs, act, aux)
        self.pos = int(idx[-1] + 1) % self.capacity
        self.size = min(self.size + act.shape[0], self.capacity)
        self.added += act.shape[0]

    def _put(self, idx: torch.Tensor, obs: dict[str, torch.Tensor], act: torch.Tensor, aux: Optional[torch.Tensor]):
        if self.act is None:
            self.obs = {k: torch.empty((self.capacity,) + v.shape[1:], dtype=v.dtype) for k, v in obs.items()}
            self.act = torch.empty((self.capacity,) + act.shape[1:], dtype=torch.float32)
            if aux is not None:
                self.aux = torch.empty((self.capacity,) + aux.shape[1:], dtype=torch.float32)
        if (aux is None) != (self.aux is None):
            raise ValueError("a dataset's rows either all carry auxiliary targets or none does")
        for k, v in obs.items():
            self.obs[k][idx] = v.cpu()
        self.act[idx] = act.float().cpu()
        if aux is not None:
            self.aux[idx] = aux.float().cpu()

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
            # a full ring's oldest row is at pos: count the rows so that added % capacity == pos
            self.added = d["size"] if d["size"] < d["capacity"] else d["capacity"] + d["pos"]

    def save_new_rows(self, folder: Path, manifest: Optional[dict]) -> dict:
        """Write the rows added since ``manifest`` (what the last call returned; None: nothing written yet) to a
        file of their own in ``folder`` and return the new manifest, which a checkpoint keeps instead of the rows.

        A save then costs the new rows, not the whole dataset: a camera run's dataset grows to gigabytes, and
        writing it whole every few rounds spent the training budget on disk writes. Files whose rows the ring has
        since overwritten leave the manifest (:func:`prune_row_files` deletes them once the checkpoint is written).
        """
        folder = Path(folder)
        files = [f for f in (manifest or {}).get("files", []) if f["end"] > self.added - self.size]
        start = max((manifest or {}).get("added", 0), self.added - self.size)
        if self.added > start:
            slots = torch.arange(start, self.added) % self.capacity
            name = f"rows_{start:010d}_{self.added:010d}.pt"
            rows = dict(  # indexing by a tensor copies: only the new rows go to torch.save
                obs={k: v[slots] for k, v in self.obs.items()},
                act=self.act[slots],
                aux=self.aux[slots] if self.aux is not None else None,
            )
            atomic_save(rows, folder / name)
            files.append(dict(name=name, start=start, end=self.added))
        return dict(capacity=self.capacity, added=self.added, files=files)

    def load_rows(self, folder: Path, manifest: dict) -> None:
        """The dataset :meth:`save_new_rows` wrote, each row back in its slot (so sampling continues as it would
        have)."""
        self.__init__(manifest["capacity"])
        for f in manifest["files"]:
            path = Path(folder) / f["name"]
            if not path.is_file():
                raise FileNotFoundError(f"the checkpoint's dataset rows {path} are missing (copy {folder} with it)")
            rows = torch.load(path, weights_only=True)
            self._put(torch.arange(f["start"], f["end"]) % self.capacity, rows["obs"], rows["act"], rows["aux"])
        self.added = manifest["added"]
        self.size, self.pos = min(self.added, self.capacity), self.added % self.capacity


def restore_dataset(data: Dataset, saved: dict, data_dir: Path, part: Optional[str] = None) -> None:
    """Refill ``data`` for a resumed run from where the checkpoint ``saved`` keeps its rows: the row files in
    ``data_dir`` (``/ part``) its ``data_rows`` manifest lists, or, with no manifest, the rows inside the checkpoint
    (under ``part``, or ``"data"``). ``part`` names one of several datasets a trainer keeps (SAC's ``online`` and
    ``demos``)."""
    manifest = saved.get("data_rows")
    if manifest is None:
        data.load_state_dict(saved[part or "data"])
    elif part is None:
        data.load_rows(data_dir, manifest)
    else:
        data.load_rows(Path(data_dir) / part, manifest[part])


def prune_row_files(folder: Path, manifest: dict) -> None:
    """Delete the row files a written checkpoint's manifest no longer lists (overwritten by the ring, or left by
    a save that never finished)."""
    keep = {f["name"] for f in manifest["files"]}
    for path in Path(folder).glob("rows_*.pt"):
        if path.name not in keep:
            path.unlink()
