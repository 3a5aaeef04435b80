"""Network pieces every policy shares (PPO, DAgger, SAC, RLlib's RLModule): one definition of the RGB-D +
proprioception encoder, so a checkpoint's encoder means the same thing everywhere; plus the deterministic actor
(BC, DAgger) and DrQ's image augmentation."""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch
import torch.nn as nn


def layer_init(layer: nn.Module, std: float = np.sqrt(2), bias: float = 0.0) -> nn.Module:
    nn.init.orthogonal_(layer.weight, std)
    nn.init.constant_(layer.bias, bias)
    return layer


def image_tensor(obs: dict[str, torch.Tensor], max_depth_mm: float = 2000.0) -> torch.Tensor:
    """(N,H,W,3) uint8 RGB + (N,H,W,1) int16 depth in mm -> (N,4,H,W) floats in [0,1]."""
    rgb = obs["rgb"].float() / 255.0
    depth = obs["depth"].float().clamp(0, max_depth_mm) / max_depth_mm
    return torch.cat([rgb, depth], dim=-1).permute(0, 3, 1, 2)


class NatureCNN(nn.Module):
    """The original report's 3-layer CNN over the 84x84x4 RGB-D image, plus a small MLP for proprioception."""

    def __init__(self, image_shape: Optional[tuple[int, int, int]], state_dim: int, feature_dim: int = 256):
        super().__init__()
        self.out_dim = 0
        self.cnn = None
        if image_shape is not None:
            h, w, c = image_shape
            self.cnn = nn.Sequential(
                nn.Conv2d(c, 32, 8, stride=4),
                nn.ReLU(),
                nn.Conv2d(32, 64, 4, stride=2),
                nn.ReLU(),
                nn.Conv2d(64, 64, 3, stride=1),
                nn.ReLU(),
                nn.Flatten(),
            )
            with torch.no_grad():
                n = self.cnn(torch.zeros(1, c, h, w)).shape[1]
            self.cnn.append(nn.Linear(n, feature_dim))
            self.cnn.append(nn.ReLU())
            self.out_dim += feature_dim
        self.mlp = nn.Sequential(nn.Linear(state_dim, 256), nn.ReLU())
        self.out_dim += 256

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        # the proprioception float32 even under a learner's bf16 autocast, as in KeypointCNN: the convolutions
        # are what autocast is for, and bf16 would round the normalised joint state to 3 significant digits
        with torch.autocast(device_type=obs["state"].device.type, enabled=False):
            feats = [self.mlp(obs["state"].float())]
        if self.cnn is not None:
            feats.insert(0, self.cnn(image_tensor(obs)))
        return torch.cat(feats, dim=1)


class SpatialSoftmax(nn.Module):
    """(N, C, H, W) feature maps -> (N, 2C): each map's expected image coordinates in [-1, 1] under a softmax
    over its pixels (Levine et al. 2016), with a learned temperature -- where a feature is, to sub-pixel precision."""

    def __init__(self, h: int, w: int):
        super().__init__()
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
        self.register_buffer("grid", torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=1))  # (HW, 2)
        self.log_temperature = nn.Parameter(torch.zeros(()))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, c, h, w = x.shape
        # float32 even under a learner's bf16 autocast: bf16's 8-bit mantissa would round the coordinates to
        # ~0.1 pixel, the precision the keypoints are for
        with torch.autocast(device_type=x.device.type, enabled=False):
            attn = torch.softmax(x.float().reshape(n * c, h * w) / self.log_temperature.exp(), dim=1)
            return (attn @ self.grid).reshape(n, 2 * c)


class KeypointCNN(nn.Module):
    """The camera encoder for precise positioning (``encoder="keypoints"``): a small conv stack at 21x21
    resolution and a spatial softmax, so the features are where things are in the image (the cube a few pixels
    wide, the fingers over it) rather than a flattened map; plus the same proprioception MLP as
    :class:`NatureCNN`. About the Nature CNN's cost per image on a CPU.

    ``depth_keypoints`` > 0 (``encoder="keypoints-depth"``) adds a second stack of the same shape that sees the
    depth image alone, with keypoints of its own: features no texture or colour can move, which the RGB-D stack
    is free to neglect when the colours tell it more on its training data. Its keypoints come between the RGB-D
    stack's and the proprioception's, so that a ``keypoints`` actor widens into this one
    (:meth:`DeterministicActor.widen`)."""

    def __init__(
        self, image_shape: tuple[int, int, int], state_dim: int, keypoints: int = 32, depth_keypoints: int = 0
    ):
        super().__init__()
        h, w, c = image_shape
        self.cnn = self.stack(c, keypoints)
        with torch.no_grad():
            _, _, fh, fw = self.cnn(torch.zeros(1, c, h, w)).shape
        self.keypoints = SpatialSoftmax(fh, fw)
        self.depth_cnn = self.depth_keypoints = None
        if depth_keypoints > 0:
            self.depth_cnn = self.stack(1, depth_keypoints)
            self.depth_keypoints = SpatialSoftmax(fh, fw)
        self.mlp = nn.Sequential(nn.Linear(state_dim, 256), nn.ReLU())
        self.image_dim = 2 * keypoints
        self.depth_dim = 2 * depth_keypoints
        self.out_dim = self.image_dim + self.depth_dim + 256

    @staticmethod
    def stack(channels: int, keypoints: int) -> nn.Sequential:
        return nn.Sequential(
            nn.Conv2d(channels, 32, 5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv2d(32, 32, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(32, 32, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(32, keypoints, 1),
        )

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        image = image_tensor(obs)
        feats = [self.keypoints(self.cnn(image))]
        if self.depth_cnn is not None:
            feats.append(self.depth_keypoints(self.depth_cnn(image[:, 3:])))
        # the proprioception float32 even under a learner's bf16 autocast (for the convolutions' sake)
        with torch.autocast(device_type=feats[0].device.type, enabled=False):
            return torch.cat([*feats, self.mlp(obs["state"].float())], dim=1)


ENCODERS = ("nature", "keypoints", "keypoints-depth")
"""the camera encoders a trainer can be asked for by name"""

DEPTH_KEYPOINTS = 16
"""the depth-only stack's keypoints in ``encoder="keypoints-depth"``: half the RGB-D stack's"""


def camera_encoder(encoder: str, image_shape: Optional[tuple[int, int, int]], state_dim: int) -> nn.Module:
    """The encoder named ``encoder`` (one of :data:`ENCODERS`), for every trainer that offers the choice."""
    if encoder not in ENCODERS:
        raise ValueError(f"unknown encoder {encoder!r}; expected one of {ENCODERS}")
    if encoder == "nature":
        return NatureCNN(image_shape, state_dim)
    if image_shape is None:
        raise ValueError(f"encoder {encoder!r} reads the camera; a state policy has no image (use 'nature')")
    return KeypointCNN(image_shape, state_dim, depth_keypoints=DEPTH_KEYPOINTS if encoder == "keypoints-depth" else 0)


def random_shift(
    obs: dict[str, torch.Tensor], pad: int = 4, generator: Optional[torch.Generator] = None
) -> dict[str, torch.Tensor]:
    """DrQ's augmentation: replicate-pad each image by ``pad`` pixels and crop it back at a random offset
    (one offset per sample, shared by RGB and depth so they stay registered; the other keys as they are).
    ``generator``: the offsets' random stream (on the images' device; default torch's global one).

    Replicate padding then cropping at offset d is reading the image at ``clamp(i + d - pad, 0, size - 1)``:
    one ``index_select`` of whole pixels per image in its own dtype (uint8, int16), where padding needs floats.
    It runs on every camera minibatch; the float round trip through a padded copy took about a tenth of a
    DAgger update."""
    rgb, depth = obs["rgb"], obs["depth"]
    n, h, w, _ = rgb.shape
    dev = rgb.device
    dx = torch.randint(0, 2 * pad + 1, (n,), device=dev, generator=generator)
    dy = torch.randint(0, 2 * pad + 1, (n,), device=dev, generator=generator)
    rows = (dy[:, None] - pad + torch.arange(h, device=dev)).clamp(0, h - 1)  # (n, h)
    cols = (dx[:, None] - pad + torch.arange(w, device=dev)).clamp(0, w - 1)  # (n, w)
    pixel = (torch.arange(n, device=dev)[:, None, None] * h + rows[:, :, None]) * w + cols[:, None, :]
    pixel = pixel.reshape(-1)  # (n·h·w,) flat pixel index of each output pixel

    def crop(img: torch.Tensor) -> torch.Tensor:
        return img.reshape(n * h * w, -1).index_select(0, pixel).view(img.shape)

    return dict(obs, rgb=crop(rgb), depth=crop(depth))


def drop_rgb(
    obs: dict[str, torch.Tensor], p: float, generator: Optional[torch.Generator] = None
) -> dict[str, torch.Tensor]:
    """Modality dropout: each sample's RGB image blacked out with probability ``p`` (its depth and the other keys
    kept), so that the encoder must localise from the depth as well and cannot rest on colours and textures alone,
    which a real cell's surfaces and light change and its geometry does not. ``generator``: the draws' stream (on
    the images' device; default torch's global one)."""
    rgb = obs["rgb"]
    gone = torch.rand(rgb.shape[0], device=rgb.device, generator=generator) < p
    return dict(obs, rgb=rgb.masked_fill(gone.view(-1, *[1] * (rgb.dim() - 1)), 0))


_RGB_TO_YIQ = torch.tensor([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]])
"""NTSC YIQ: luma Y and the chroma plane (I, Q), in which a hue shift is a rotation and saturation a scale"""
_YIQ_TO_RGB = torch.linalg.inv(_RGB_TO_YIQ)


def jitter_rgb(
    obs: dict[str, torch.Tensor], strength: float, generator: Optional[torch.Generator] = None
) -> dict[str, torch.Tensor]:
    """Photometric augmentation (RAD's and torchvision's colour jitter): each sample's RGB image gets its own
    brightness and contrast factor and saturation scale in ``1 ± strength`` and its own hue rotation in
    ``± strength × 180°``, so that a learner cannot rest on the absolute colours of the cube, the trays and the
    table, which a real cell's surfaces change and its geometry does not. At ``strength`` 1 the saturation can reach 0
    (grey). The depth and the other keys are kept; the images stay uint8. ``generator``: the draws' stream (on the
    images' device; default torch's global one).

    Colour and contrast make one affine map per sample (to YIQ, scale and rotate the chroma plane, back; then scale
    about the image's mean luma, as torchvision's ``adjust_contrast``), applied with one batched ``baddbmm``: it
    costs about a tenth of a camera minibatch update on 2 cores."""
    if strength == 0:
        return obs
    rgb = obs["rgb"]
    n, dev = rgb.shape[0], rgb.device

    def factor() -> torch.Tensor:
        return (torch.rand(n, device=dev, generator=generator) * 2 - 1) * strength

    brightness, contrast, saturation = 1 + factor(), 1 + factor(), (1 + factor()).clamp(min=0)
    angle = factor() * torch.pi
    cos, sin = torch.cos(angle) * saturation, torch.sin(angle) * saturation
    chroma = torch.zeros(n, 3, 3, device=dev)
    chroma[:, 0, 0] = 1
    chroma[:, 1, 1], chroma[:, 1, 2], chroma[:, 2, 1], chroma[:, 2, 2] = cos, -sin, sin, cos
    to_yiq = _RGB_TO_YIQ.to(dev)
    colour = _YIQ_TO_RGB.to(dev) @ chroma @ to_yiq * brightness.view(n, 1, 1)  # (n, 3, 3)
    x = rgb.float().reshape(n, -1, 3)  # (n, h*w, 3), 0..255
    mean_luma = (colour @ x.mean(1, keepdim=True).transpose(1, 2)).squeeze(2) @ to_yiq[0]  # (n,) after the colour
    offset = ((1 - contrast) * mean_luma).view(n, 1, 1).expand(n, 1, 3)
    out = torch.baddbmm(offset, x, (colour * contrast.view(n, 1, 1)).transpose(1, 2))
    return dict(obs, rgb=out.add_(0.5).clamp_(0, 255).to(rgb.dtype).view(rgb.shape))  # rounded (non-negative)


CONSTANT_STD = 1e-3
"""a state dimension whose spread in the fitting data is below this (SI units: m, rad, rad/s) carried no
information there: StateNorm zeroes it instead of scaling it up"""


def usable_std(std: torch.Tensor) -> torch.Tensor:
    """``std`` with the dimensions below ``CONSTANT_STD`` set to +inf: a dimension that did not vary is read as
    zero, never amplified (both state normalisers' rule; StateNorm says why)."""
    return torch.where(std < CONSTANT_STD, torch.full_like(std, float("inf")), std)


class StateNorm(nn.Module):
    """Fixed per-dimension standardisation of the ``state`` vector, fitted once on the first data
    (joint velocities and positions differ by orders of magnitude; an MLP learns faster on unit scales).

    A dimension that did not vary in that data (the IRB 120's axis 4, which the tool-frame IK keeps at zero; the
    trays' fixed positions) is zeroed (std +inf): a policy cannot have learned anything from it, and scaled up by
    the old 1e-3 floor, a real robot's 0.02° on axis 4 (float32 RAPID, the protocol's resolution) read as a
    7-sigma joint speed and turned a state DAgger policy's grasp around on the digital twin."""

    def __init__(self, dim: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))

    def fit(self, x: torch.Tensor) -> None:
        std = x.float().std(0)
        self.mean.copy_(x.float().mean(0))
        self.std.copy_(usable_std(std))

    def forward(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return dict(obs, state=(obs["state"].float() - self.mean) / self.std)


class RunningNorm(nn.Module):
    """Standardisation of the ``state`` vector by running statistics (gym's ``NormalizeObservation``, kept in the
    policy so a checkpoint acts as it trained), clipped to ±``clip``.

    For learners from scratch, whose data changes as they learn: the state mixes metres of position with the
    millimetres a grasp needs (``tcp_to_obj_pos``), and only unit scales let an MLP resolve both. The trainer
    calls :meth:`update` between updates, never inside one (the log-probabilities of a rollout stay valid);
    a dimension that has not varied is zeroed, as in :class:`StateNorm`."""

    def __init__(self, dim: int, clip: float = 10.0):
        super().__init__()
        self.clip = clip
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("var", torch.ones(dim))
        self.register_buffer("count", torch.zeros(()))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Merge a batch's (B, dim) moments into the running ones (Chan et al.'s parallel algorithm)."""
        x = x.float().reshape(-1, self.mean.numel())
        n = x.shape[0]
        if n == 0:
            return
        mean, var = x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        delta = mean - self.mean
        self.var.copy_((self.var * self.count + var * n + delta**2 * self.count * n / total) / total)
        self.mean.add_(delta * n / total)
        self.count.copy_(total)

    def forward(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        std = usable_std(self.var.sqrt())
        return dict(obs, state=((obs["state"].float() - self.mean) / std).clamp(-self.clip, self.clip))


class DeterministicActor(nn.Module):
    """Observation -> action in [-1, 1]: the shared encoder, then a 2-layer MLP and tanh (BC, DAgger)."""

    def __init__(
        self,
        image_shape: Optional[tuple[int, int, int]],
        state_dim: int,
        action_dim: int,
        hidden: int = 512,
        encoder: str = "nature",
    ):
        super().__init__()
        self.encoder = camera_encoder(encoder, image_shape, state_dim)
        self.image_shape, self.state_dim, self.action_dim = image_shape, state_dim, action_dim
        self.encoder_kind = encoder
        self.norm = StateNorm(state_dim)
        self.head = nn.Sequential(
            nn.Linear(self.encoder.out_dim, hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
            nn.Linear(hidden, action_dim),
        )

    def signature(self) -> dict:
        sig = dict(
            image_shape=list(self.image_shape) if self.image_shape else None,
            state_dim=self.state_dim,
            action_dim=self.action_dim,
        )
        if self.encoder_kind != "nature":  # the Nature CNN's signature predates the choice: old checkpoints load
            sig["encoder"] = self.encoder_kind
        return sig

    def widen(self, narrow: dict[str, torch.Tensor]) -> None:
        """Load a ``keypoints`` actor's weights (its ``state_dict``) into this ``keypoints-depth`` one so that it acts
        exactly as that actor did: the depth stack keeps its fresh weights, and the head's first layer reads its
        keypoints through zero columns. Training then grows those columns from their gradient (which is not zero),
        and with them the depth stack's, from the narrow policy's behaviour rather than from scratch (Net2Net's
        function-preserving widening)."""
        if self.encoder_kind != "keypoints-depth":
            raise ValueError(f"only a 'keypoints-depth' actor widens a narrower one (this one: {self.encoder_kind!r})")
        own = self.state_dict()
        extra = {k for k in own if k.startswith(("encoder.depth_cnn.", "encoder.depth_keypoints."))}
        weight = own["head.0.weight"]
        begin, end = self.encoder.image_dim, self.encoder.image_dim + self.encoder.depth_dim
        shapes = {k: v.shape for k, v in own.items() if k not in extra}
        shapes["head.0.weight"] = torch.Size((weight.shape[0], weight.shape[1] - (end - begin)))
        if {k: v.shape for k, v in narrow.items()} != shapes:
            raise ValueError("the weights to widen are not a 'keypoints' actor's of this actor's shapes")
        wide = dict(narrow)
        wide["head.0.weight"] = torch.cat(
            [
                narrow["head.0.weight"][:, :begin],
                torch.zeros_like(weight[:, begin:end]),
                narrow["head.0.weight"][:, begin:],
            ],
            dim=1,
        )
        wide.update({k: own[k] for k in extra})
        self.load_state_dict(wide)

    def features(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """The encoder's output: what an auxiliary head (agents.dagger ``--aux-weight``) reads too."""
        return self.encoder(self.norm(obs))

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        return torch.tanh(self.head(self.features(obs)))
