"""A RealSense-like depth model for the hand camera's depth (``randomization="depth_model=d435"``).

The sim renders perfect depth; a D400-series stereo camera does not. Its error is a disparity error, so the
model works in disparity at the real camera's native resolution, where the stereo matching happens, and
maps the result onto the sim's 84x84 frame (``sim2real/cameras.py`` takes the nearest native pixel for each
sim pixel, so each sim pixel carries one native pixel's error, uncorrelated with its neighbours'):

* noise: disparity ``d = f·B / z`` (f the native focal length in px, B the baseline) gets Gaussian noise of
  ``subpixel`` px RMS, hence a depth RMS error ``z² · subpixel / (f · B)``, growing with the square of the
  distance (Intel, "Tuning depth cameras for best performance", the RMS error formula);
* quantisation: the measured disparity snaps to the grid of ``subpixel_step`` px, so depths snap to
  ``f·B / (k · subpixel_step)`` (the D4 processor's subpixel steps: Intel, "Subpixel linearity improvement");
* edges: a pixel whose 4-neighbour differs in depth by more than ``edge_jump_m`` reads 0 (the matching
  window straddles the discontinuity);
* occlusion shadow: a pixel the left imager (the depth origin) sees and the right one does not reads 0. The
  right imager sits at +x, so the shadow lies on the -u side of a near object, as wide as the disparity
  difference; the projector sits between the imagers, so its shadow falls inside this one;
* range: measured depths below ``min_m`` (the disparity search's limit, by resolution) or above ``max_m`` read 0;
* dark and specular surfaces: a pixel darker than ``dark_level`` (mean RGB in [0, 1]) drops with a probability
  rising linearly to ``dark_dropout`` at black; one brighter than ``specular_level`` (a saturated highlight)
  drops with ``specular_dropout``.

The presets, at the resolution Intel recommends for depth (848x480):

| preset | baseline | focal (native) | subpixel RMS | step | min range | max range | source |
|---|---|---|---|---|---|---|---|
| ``d435`` | 50 mm | 424 px (HFOV 90°) | 0.08 px | 1/32 px | 0.195 m | 3 m | D400 datasheet; tuning paper |
| ``d405`` | 18 mm | 447 px (HFOV 87°) | 0.08 px | 1/32 px | 0.07 m | 0.5 m | D400 datasheet (D401/D405) |

Baselines, fields of view and minimum ranges (Min-Z at 848x480) are the datasheet's (Intel RealSense D400
Series datasheet, 337029); 0.08 px is the tuning paper's typical subpixel RMS for a well-textured scene, and
the D405 (same D4 processor) is given the same; the max range is the upper end of the datasheet's "ideal
range" (the camera still reports beyond it, with an error the quadratic law makes large). The edge threshold
and the dark/specular dropout figures (0.5 at black; 0.8 for the D405, which has no projector to texture a dark
surface) are modelling choices, not measurements: fit them on real frames.

Everything is batched torch on (num_envs, H, W, 1) int16 mm depth, on the CPU or CUDA, without host syncs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


def drawn(sample, shape, generator: torch.Generator | None, device: torch.device) -> torch.Tensor:
    """``sample`` (torch.randn / torch.rand) of ``shape`` on ``device``, drawn on the generator's own device: on a
    GPU machine the CPU sim's frames live on CUDA while its generator stays on the CPU."""
    on = device if generator is None else generator.device
    return sample(shape, generator=generator, device=on).to(device)


@dataclass(frozen=True)
class DepthModel:
    name: str
    baseline_m: float
    focal_px: float  # the depth imager's at its native resolution
    subpixel: float = 0.08  # disparity RMS error, px
    subpixel_step: float = 1 / 32  # disparity quantum, px
    min_m: float = 0.195
    max_m: float = 3.0
    edge_jump_m: float = 0.01
    dark_level: float = 0.15
    dark_dropout: float = 0.5
    specular_level: float = 0.98
    specular_dropout: float = 0.5

    def __post_init__(self):
        for k in ("baseline_m", "focal_px", "subpixel_step", "min_m", "edge_jump_m", "dark_level"):
            if not getattr(self, k) > 0:
                raise ValueError(f"depth model {self.name!r}: {k} must be > 0, got {getattr(self, k)!r}")
        if self.subpixel < 0 or self.max_m <= self.min_m:
            raise ValueError(f"depth model {self.name!r}: needs subpixel >= 0 and max_m > min_m")
        for k in ("dark_dropout", "specular_dropout"):
            if not 0 <= getattr(self, k) <= 1:
                raise ValueError(f"depth model {self.name!r}: {k} is a probability in [0, 1]")

    def rms_error_m(self, z_m: float) -> float:
        """The depth RMS error at ``z_m`` metres (Intel's formula)."""
        return z_m**2 * self.subpixel / (self.focal_px * self.baseline_m)

    def max_shadow_px(self, focal_sim_px: float) -> int:
        """The widest occlusion shadow in sim pixels: the disparity at the minimum range."""
        return math.ceil(focal_sim_px * self.baseline_m / self.min_m)

    def apply(
        self,
        depth: torch.Tensor,
        rgb: torch.Tensor | None,
        focal_sim_px: torch.Tensor | float,
        generator: torch.Generator | None = None,
        max_focal_sim_px: float | None = None,
    ) -> torch.Tensor:
        """``depth`` (N, H, W, 1) int16 mm (0: no reading) as the camera would measure it; ``rgb`` (N, H, W, 3)
        uint8 or None (no dark/specular dropout then); ``focal_sim_px`` the sim camera's focal length, per env
        (N,) or one for all, and ``max_focal_sim_px`` its largest value (bounds the shadow search without
        reading the device)."""
        if depth.ndim != 4 or depth.shape[-1] != 1:
            raise ValueError(f"depth must be (num_envs, H, W, 1), got {tuple(depth.shape)}")
        if rgb is not None and (rgb.shape[:3] != depth.shape[:3] or rgb.shape[-1] != 3):
            raise ValueError(f"rgb {tuple(rgb.shape)} does not match depth {tuple(depth.shape)}")
        dev = depth.device
        z = depth[..., 0].float() / 1000.0  # (N, H, W) m
        valid = depth[..., 0] > 0
        f_sim = torch.as_tensor(focal_sim_px, dtype=torch.float32, device=dev).reshape(-1, 1, 1)
        if max_focal_sim_px is None:
            max_focal_sim_px = float(focal_sim_px if isinstance(focal_sim_px, float | int) else f_sim.max())
        invalid = ~valid | self._edges(z, valid) | self._shadow(z, valid, f_sim, max_focal_sim_px)

        fb = self.focal_px * self.baseline_m
        disparity = fb / z.clamp_min(1e-6)
        noise = drawn(torch.randn, z.shape, generator, dev)
        measured = torch.round((disparity + noise * self.subpixel) / self.subpixel_step) * self.subpixel_step
        z_out = fb / measured.clamp_min(self.subpixel_step)
        invalid |= (measured < self.subpixel_step) | (z_out < self.min_m) | (z_out > self.max_m)

        u = drawn(torch.rand, z.shape, generator, dev)
        if rgb is not None:
            b = rgb.float().mean(-1) / 255.0
            p = self.dark_dropout * ((self.dark_level - b) / self.dark_level).clamp(0, 1)
            p = torch.where(b >= self.specular_level, torch.full_like(p, self.specular_dropout), p)
            invalid |= u < p
        mm = torch.round(z_out * 1000.0).clamp(0, 32767)
        return torch.where(invalid, 0.0, mm).to(depth.dtype)[..., None]

    def _edges(self, z: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Pixels with a 4-neighbour more than ``edge_jump_m`` away in depth (both having a reading)."""
        zz = torch.where(valid, z, torch.inf)
        out = torch.zeros_like(valid)
        for dim in (1, 2):
            jump = (zz.diff(dim=dim).abs() > self.edge_jump_m) & zz.isfinite().narrow(dim, 0, zz.shape[dim] - 1)
            jump &= zz.isfinite().narrow(dim, 1, zz.shape[dim] - 1)
            pad = [0, 0, 0, 0]
            pad[2 * (2 - dim) + 1] = 1  # after: the first pixel of each pair
            out |= torch.nn.functional.pad(jump, pad)
            pad = [0, 0, 0, 0]
            pad[2 * (2 - dim)] = 1  # before: the second
            out |= torch.nn.functional.pad(jump, pad)
        return out & valid

    def _shadow(self, z: torch.Tensor, valid: torch.Tensor, f_sim: torch.Tensor, max_f: float) -> torch.Tensor:
        """Pixels u the right imager cannot see: some pixel u + j (j >= 1) is nearer by a disparity of at least
        j sim pixels, so it covers u's ray from the right imager."""
        disp = torch.where(valid, f_sim * self.baseline_m / z.clamp_min(1e-6), 0.0)  # sim px
        out = torch.zeros_like(valid)
        w = z.shape[2]
        for j in range(1, min(self.max_shadow_px(max_f), w - 1) + 1):
            out[:, :, : w - j] |= disp[:, :, j:] - disp[:, :, : w - j] >= j
        return out & valid


PRESETS: dict[str, DepthModel] = {
    "d435": DepthModel("d435", baseline_m=0.050, focal_px=424.0, min_m=0.195, max_m=3.0),
    # no projector on the D405: dark, untextured surfaces have only ambient texture to match on
    "d405": DepthModel(
        "d405", baseline_m=0.018, focal_px=424.0 / math.tan(math.radians(43.5)), min_m=0.07, max_m=0.5, dark_dropout=0.8
    ),
}


def preset(name: str) -> DepthModel:
    try:
        return PRESETS[name.strip().lower()]
    except KeyError:
        raise ValueError(f"depth_model={name!r}: one of {sorted(PRESETS)} (or 'off')") from None
