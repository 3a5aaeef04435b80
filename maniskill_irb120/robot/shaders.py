"""Sensor shading for fast CPU rendering.

ManiSkill's ``minimal`` shader pack draws a frame in two passes: a G-buffer pass that already computes
the lit colour, then a full-screen composite that only fills the background from the environment
map. On lavapipe (software Vulkan, the no-GPU path) every pass and every per-vertex 4x4 inverse is
CPU time. ``rgbd_forward`` (``assets/shaders/rgbd_forward``) does the same lighting in one pass and
writes ManiSkill's ``minimal`` outputs directly: ``Color`` (RGBA8) and ``PositionSegmentation``
(int16 millimetres + segmentation id), so ManiSkill's own texture transforms apply unchanged. In our
scene it gives the same RGB-D images as ``minimal`` (tested) at about two thirds of the frame time.

Select a pack per camera with ManiSkill's usual override, e.g.
``gym.make(..., sensor_configs=dict(hand_camera=dict(shader_pack="minimal")))``.
"""

from __future__ import annotations

from importlib import resources

import sapien
from mani_skill.render.shaders import PREBUILT_SHADER_CONFIGS, ShaderConfig

FORWARD = "rgbd_forward"


def forward_shader_dir() -> str:
    return str(resources.files("maniskill_irb120.assets").joinpath("shaders", FORWARD))


def sensor_shader_config(name: str = FORWARD) -> ShaderConfig:
    """ShaderConfig for a sensor camera: ours (``rgbd_forward``) or any of ManiSkill's prebuilt packs.

    SAPIEN binds a camera's picture formats when the camera is created, from a process-wide setting
    that ManiSkill only sets for its own packs; ours sets the ``minimal`` formats here, right before
    the camera that uses it is built.
    """
    if name == FORWARD:
        sapien.render.set_picture_format("Color", "r8g8b8a8unorm")
        sapien.render.set_picture_format("PositionSegmentation", "r16g16b16a16sint")
        minimal = PREBUILT_SHADER_CONFIGS["minimal"]
        return ShaderConfig(
            shader_pack=forward_shader_dir(),
            texture_names=dict(minimal.texture_names),
            texture_transforms=dict(minimal.texture_transforms),
        )
    if name in PREBUILT_SHADER_CONFIGS:
        return PREBUILT_SHADER_CONFIGS[name]
    raise ValueError(f"unknown sensor shader {name!r}; use {FORWARD!r} or one of {sorted(PREBUILT_SHADER_CONFIGS)}")
