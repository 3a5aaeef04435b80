"""Appearance randomisation a hand camera needs: procedural textures, colours and surface materials of the table,
the trays, the floor and the objects, per env and per episode, seeded.

A camera on the hand sees the table and the trays fill most of its frame, and a real cell's table is wood, steel or
a printed mat, never the sim's flat colour; a green screen behind the scene (ManiSkill's fixed-camera recipe) would
be seen from a different angle every step. So the levers are the surfaces themselves (MuJoCo Playground randomises
``geom_rgba`` and ``geom_matid`` per world for the same reason).

- ``draw_texture``: one of four pattern families (smooth blotches like stone or wood, a checker, stripes,
  fine grain) at a random scale, orientation and contrast, multiplied onto the surface's colour. Our sensor shader
  (``assets/shaders/rgbd_forward``) takes the texture as the albedo, so the colour goes into the texture: a yellow
  tray stays yellow, patterned.
- ``roughness`` and ``specular`` set the GGX terms the same shader uses (highlights on a glossy table).

Textures need texture coordinates: the merged box meshes carry planar ones (``robot/description.merged_box_mesh``),
one tile per ``TEXTURE_TILE_M``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sapien

TEXTURE_SIZE = 64  # texels a side; ~1 texel per hand-camera pixel at the table's distance
PATTERNS = ("blotches", "checker", "stripes", "grain")


@dataclass(frozen=True)
class Texture:
    """One drawn texture and what was drawn for it, so an analysis can tell which patterns a policy fails on."""

    rgba: np.ndarray
    """(size, size, 4) uint8, the albedo"""
    pattern: int
    """its family, an index into PATTERNS"""
    contrast: float
    """how far the pattern darkens the colour at its darkest, 0..1"""


def draw_texture(rng: np.random.Generator, rgb, size: int = TEXTURE_SIZE) -> Texture:
    """``rgb`` (0..1) modulated by a random pattern, with the pattern's family and contrast. The pattern tiles
    seamlessly (every family is periodic over the texture), as the texture repeats over a surface."""
    index = int(rng.integers(len(PATTERNS)))
    kind = PATTERNS[index]
    y, x = np.mgrid[0:size, 0:size] / size  # [0, 1) on both axes
    if kind == "blotches":
        cells = int(rng.integers(2, 7))
        coarse = rng.random((cells, cells))
        # bilinear upsampling of a periodic grid: smooth, tileable blotches
        fx, fy = x * cells, y * cells
        x0, y0 = np.floor(fx).astype(int), np.floor(fy).astype(int)
        tx, ty = fx - x0, fy - y0
        x1, y1 = (x0 + 1) % cells, (y0 + 1) % cells
        pattern = (
            coarse[y0, x0] * (1 - tx) * (1 - ty)
            + coarse[y0, x1] * tx * (1 - ty)
            + coarse[y1, x0] * (1 - tx) * ty
            + coarse[y1, x1] * tx * ty
        )
    elif kind == "checker":
        n = int(rng.integers(1, 5)) * 2
        pattern = ((np.floor(x * n) + np.floor(y * n)) % 2).astype(float)
    elif kind == "stripes":
        kx, ky = rng.integers(-4, 5, size=2)
        if kx == 0 and ky == 0:
            kx = 1
        pattern = 0.5 + 0.5 * np.sin(2 * np.pi * (kx * x + ky * y) + rng.uniform(0, 2 * np.pi))
    else:
        pattern = rng.random((size, size))
    contrast = rng.uniform(0.15, 0.6)
    tint = rng.uniform(0.85, 1.15, size=3)  # a pattern in a slightly other hue, as wood grain or a print
    shade = 1.0 - contrast * pattern[..., None] * tint
    out = np.clip(np.asarray(rgb, dtype=np.float64)[:3] * shade, 0.0, 1.0)
    rgba = np.concatenate([np.rint(out * 255), np.full((size, size, 1), 255.0)], axis=2).astype(np.uint8)
    return Texture(rgba, index, float(contrast))


def render_shapes_per_env(actor) -> dict[int, list]:
    """Env index -> the render shapes of that env's entity of ``actor`` (ManiSkill's merged actors keep one entity
    per env, in ``_scene_idxs`` order)."""
    out: dict[int, list] = {}
    for obj, i in zip(actor._objs, actor._scene_idxs.cpu().numpy().tolist()):
        body = obj.find_component_by_type(sapien.render.RenderBodyComponent)
        out.setdefault(int(i), []).extend(body.render_shapes if body is not None else [])
    return out


def set_texture(material: sapien.render.RenderMaterial, texture: np.ndarray | None) -> None:
    """The material's albedo texture (None: its plain base colour again)."""
    material.base_color_texture = (
        None if texture is None else sapien.render.RenderTexture2D(texture, "R8G8B8A8Unorm", srgb=False)
    )
