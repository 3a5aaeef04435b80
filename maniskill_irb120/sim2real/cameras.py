"""Cameras for the real agent, each returning what the sim's hand camera returns: RGB uint8 (H, W, 3) and depth
int16 millimetres (H, W, 1), 84x84 with the sim camera's field of view.

``RealSenseCamera`` (``pyrealsense2``, optional): depth aligned to colour, then :func:`to_sim_frame` crops the
sim camera's field of view out of the real one around the principal point and resizes it. ``TwinCamera``: the
hand camera rendered in the digital twin behind the controller emulator.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

SIM_SIZE = 84
SIM_FOV_DEG = 90.0  # the hand camera's (agents/irb120.py HAND_CAMERA), square image: same both ways


def to_sim_frame(
    rgb: np.ndarray,
    depth_mm: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    fov_deg: float = SIM_FOV_DEG,
    size: int = SIM_SIZE,
) -> tuple[np.ndarray, np.ndarray]:
    """Crop the pinhole view of ``fov_deg`` out of a real frame with intrinsics (fx, fy, cx, cy) in pixels, and
    resize it to ``size``x``size``. Colour is area-averaged; depth takes the nearest pixel (averaging would
    invent depths at edges and mix in the zeros that mean "no reading"). Depth in, uint16 or int16 mm; out,
    int16 mm, saturating at 32767 (ManiSkill's depth format)."""
    rgb, depth_mm = np.asarray(rgb), np.asarray(depth_mm)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be uint8 (H, W, 3), got {rgb.dtype} {rgb.shape}")
    depth2 = depth_mm[..., 0] if depth_mm.ndim == 3 and depth_mm.shape[2] == 1 else depth_mm
    if depth2.shape != rgb.shape[:2]:
        raise ValueError(f"depth {depth_mm.shape} is not aligned to colour {rgb.shape}: align it first")
    t = math.tan(math.radians(fov_deg) / 2)
    half_w, half_h = fx * t, fy * t
    x0, x1, y0, y1 = cx - half_w, cx + half_w, cy - half_h, cy + half_h
    h, w = depth2.shape
    if x0 < -0.5 or y0 < -0.5 or x1 > w - 0.5 or y1 > h - 0.5:
        have = 2 * math.degrees(math.atan(min(cx + 0.5, w - 0.5 - cx) / fx))
        raise ValueError(
            f"the camera sees {have:.1f} deg across at most, less than the sim's {fov_deg:.1f} deg: "
            f"train with hand_camera fov (or the camera_fov randomisation) set to the real camera's"
        )
    # pixel centres of the output grid, mapped into the source (OpenCV's convention: pixel centres at integer
    # coordinates, the principal point in the same units): an exact pinhole crop, no rounding of its bounds
    u = x0 + (np.arange(size) + 0.5) * (x1 - x0) / size
    v = y0 + (np.arange(size) + 0.5) * (y1 - y0) / size
    scale = (x1 - x0) / size
    blur = rgb if scale <= 1 else cv2.blur(rgb, (max(1, round(scale)), max(1, round(scale))))
    mx, my = np.meshgrid(u.astype(np.float32), v.astype(np.float32))
    colour = cv2.remap(blur, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    d = depth2[np.clip(np.rint(v).astype(int), 0, h - 1)][:, np.clip(np.rint(u).astype(int), 0, w - 1)]
    d = np.clip(d.astype(np.int64), 0, np.iinfo(np.int16).max).astype(np.int16)
    return colour, d[..., None]


class RealSenseCamera:
    """An Intel RealSense (D400 series) on the wrist: colour and depth at ``width``x``height`` through librealsense's
    pipeline, depth aligned to colour, the depth scale and the colour intrinsics read from the device, converted
    by :func:`to_sim_frame` on every read. ``playback``: a recording (``.db3`` from librealsense 2.59, ``.bag``
    from older releases) played through the same pipeline instead of a live camera, as fast as it is read; the
    tests feed it frames recorded from a ``software_device`` (tests/sim2real/test_realsense.py)."""

    def __init__(
        self,
        width: int = 640,
        height: int = 480,
        fps: int = 30,
        fov_deg: float = SIM_FOV_DEG,
        serial=None,
        playback: str | None = None,
        timeout_ms: int = 1000,
    ):
        self.width, self.height, self.fps, self.fov_deg, self.serial = width, height, fps, fov_deg, serial
        self.playback, self.timeout_ms = playback, timeout_ms
        self.pipeline = None

    def start(self) -> None:
        try:
            import pyrealsense2 as rs
        except ImportError:
            raise ImportError("RealSenseCamera needs pyrealsense2: pip install -e '.[real]'") from None
        cfg = rs.config()
        if self.playback:
            cfg.enable_device_from_file(str(self.playback), repeat_playback=False)
        elif self.serial:
            cfg.enable_device(str(self.serial))
        cfg.enable_stream(rs.stream.color, self.width, self.height, rs.format.rgb8, self.fps)
        cfg.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16, self.fps)
        pipeline = rs.pipeline()
        source = f"the recording {self.playback}" if self.playback else f"RealSense {self.serial or '(any)'}"
        if not cfg.can_resolve(rs.pipeline_wrapper(pipeline)):
            raise RuntimeError(
                f"{source}: no {self.width}x{self.height} rgb8 colour and z16 depth at {self.fps} fps "
                "(no camera connected, or it offers other streams)"
            )
        try:
            profile = pipeline.start(cfg)
        except RuntimeError as e:
            raise RuntimeError(f"{source}: librealsense could not start it: {e}") from None
        if self.playback:
            profile.get_device().as_playback().set_real_time(False)  # every recorded frame, in order
        self.pipeline = pipeline
        self.depth_to_mm = profile.get_device().first_depth_sensor().get_depth_scale() * 1000.0
        intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        self.intrinsics = (intr.fx, intr.fy, intr.ppx, intr.ppy)
        self.align = rs.align(rs.stream.color)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        if self.pipeline is None:
            raise RuntimeError("RealSenseCamera.read() before start()")
        ok, frames = self.pipeline.try_wait_for_frames(self.timeout_ms)
        if not ok:
            raise RuntimeError(f"RealSenseCamera: no frames within {self.timeout_ms} ms (camera unplugged or stalled)")
        frames = self.align.process(frames)
        colour, depth_frame = frames.get_color_frame(), frames.get_depth_frame()
        if not colour or not depth_frame:
            missing = "colour" if not colour else "depth"
            raise RuntimeError(f"RealSenseCamera: the frameset has no {missing} frame (a dropped frame)")
        rgb = np.asanyarray(colour.get_data())
        depth = np.asanyarray(depth_frame.get_data()).astype(np.float64) * self.depth_to_mm
        return to_sim_frame(rgb, np.rint(depth), *self.intrinsics, fov_deg=self.fov_deg)

    def stop(self) -> None:
        if self.pipeline is not None:
            self.pipeline.stop()
            self.pipeline = None


class TwinCamera:
    """The hand camera of the digital twin (``DigitalTwin``): the frame its last step rendered."""

    def __init__(self, twin, name: str = "hand_camera"):
        self.twin, self.name = twin, name

    def start(self) -> None:
        pass

    def stop(self) -> None:
        pass

    def params(self) -> dict:
        return {k: v.clone() for k, v in self.twin.obs["sensor_param"][self.name].items()}

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        cam = self.twin.obs["sensor_data"][self.name]
        return cam["rgb"][0].cpu().numpy(), cam["depth"][0].cpu().numpy()
