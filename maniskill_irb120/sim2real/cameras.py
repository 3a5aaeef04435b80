"""Cameras for the real agent, each returning what the sim's hand camera returns: RGB uint8 (H, W, 3) and depth
int16 millimetres (H, W, 1), 84x84 with the sim camera's field of view.

``RealSenseCamera`` (``pyrealsense2``, optional): depth aligned to colour, then :func:`to_sim_frame` crops the
sim camera's field of view out of the real one around the principal point and resizes it. ``TwinCamera``: the
hand camera rendered in the digital twin behind the controller emulator. ``MountCorrectedCamera``: either of
them on a mount that differs from the trained one by a measured offset (hand-eye calibration), its frames
reprojected to the trained mount (:func:`reproject_to_mount`).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy import ndimage

SIM_SIZE = 84
SIM_FOV_DEG = 90.0  # the hand camera's (agents/irb120.py HAND_CAMERA), square image: same both ways
# a measured mount farther off than this is refused: a units slip (mm for m), or a camera to re-mount
MAX_MOUNT_OFFSET_M, MAX_MOUNT_TILT_DEG = 0.05, 20.0
# OpenCV's camera axes (x right, y down, z along the view) from SAPIEN's (x along the view, y left, z up)
CV_FROM_SAPIEN = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


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


def sim_intrinsics(size: int = SIM_SIZE, fov_deg: float = SIM_FOV_DEG) -> np.ndarray:
    """(3, 3) OpenCV intrinsics of the sim camera's square image (what ManiSkill reports as ``intrinsic_cv``:
    the principal point at the image centre, pixel i spanning [i, i + 1))."""
    f = size / 2 / math.tan(math.radians(fov_deg) / 2)
    return np.array([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])


def parse_mount(spec: str) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,) m, rotation (3,) deg) of a measured camera mount, written as the randomisation writes one
    (``camera_pos=0.01;-0.01;0.005,camera_rot=3;-3;5``: the same names, axes and order), fixed values only."""
    from maniskill_irb120.envs.randomization import Randomization

    r = Randomization.parse(spec)
    other = [k for k in r.active() if k not in ("camera_pos", "camera_rot")]
    if other:
        raise ValueError(f"a camera mount is camera_pos and camera_rot only, got {other} in {spec!r}")
    for name in ("camera_pos", "camera_rot"):
        v = getattr(r, name)
        if not np.isscalar(v) and len(v) != 3:
            raise ValueError(f"{name}={v!r}: a measured mount is one value per axis (x;y;z), not a range")
    draw = np.random.default_rng(0)  # fixed values: the generator is not used
    pos, rot = r.draw("camera_pos", draw)[0], r.draw("camera_rot", draw)[0]
    if np.abs(pos).max() > MAX_MOUNT_OFFSET_M or np.abs(rot).max() > MAX_MOUNT_TILT_DEG:
        raise ValueError(
            f"camera mount {spec!r}: more than {100 * MAX_MOUNT_OFFSET_M:.0f} cm or {MAX_MOUNT_TILT_DEG:.0f} deg off "
            "the trained mount (metres and degrees expected); so far off, the frame would be mostly unseen: "
            "re-mount the camera instead"
        )
    return pos, rot


def reproject_to_mount(
    rgb: np.ndarray, depth_mm: np.ndarray, pos: np.ndarray, rot_deg: np.ndarray, intrinsics: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The frame a camera on the trained mount would have seen, from one taken on a mount offset by ``pos`` (m)
    and ``rot_deg`` (the randomisation's ``camera_pos``/``camera_rot``, ``camera_mount_offset``).

    A policy trained on one mount loses its grasp when the camera sits a centimetre or a few degrees off
    (docs/notes/camera-mount.md); a depth camera lets the frame be moved back instead:
    every valid depth pixel is lifted to 3-D, moved into the trained camera's frame and projected again, the
    nearest point winning where several land on one pixel. Pixels nothing lands on (the strip the offset camera
    did not see, surfaces it saw edge-on, its own invalid readings) take the nearest reprojected pixel's colour
    and depth, so the image has no holes a policy never saw in training; a frame with no valid depth in view
    comes back as it was. Same size and intrinsics in and out:
    ``rgb`` uint8 (H, W, 3), ``depth_mm`` int16/uint16 mm (H, W, 1), 0 = no reading."""
    rgb, depth_mm = np.asarray(rgb), np.asarray(depth_mm)
    depth2 = depth_mm[..., 0] if depth_mm.ndim == 3 else depth_mm
    if rgb.ndim != 3 or rgb.shape[:2] != depth2.shape:
        raise ValueError(f"rgb {rgb.shape} and depth {depth_mm.shape} are not one aligned frame")
    from maniskill_irb120.envs.randomization import camera_mount_offset

    pose = camera_mount_offset(pos, rot_deg)  # the offset camera in the trained camera's frame (SAPIEN axes)
    rot = CV_FROM_SAPIEN @ pose.to_transformation_matrix()[:3, :3] @ CV_FROM_SAPIEN.T
    shift = CV_FROM_SAPIEN @ np.asarray(pose.p, dtype=np.float64)
    h, w = depth2.shape
    (fx, _, cx), (_, fy, cy) = intrinsics[0], intrinsics[1]
    v, u = np.nonzero(depth2 > 0)
    z = depth2[v, u].astype(np.float64)
    points = np.stack([(u + 0.5 - cx) / fx * z, (v + 0.5 - cy) / fy * z, z], 1) @ rot.T + 1000.0 * shift
    front = points[:, 2] > 1.0
    un = np.floor(fx * points[front, 0] / points[front, 2] + cx).astype(np.int64)
    vn = np.floor(fy * points[front, 1] / points[front, 2] + cy).astype(np.int64)
    inside = (un >= 0) & (un < w) & (vn >= 0) & (vn < h)
    src = np.flatnonzero(front)[inside]
    if src.size == 0:  # no depth to move it by (a D435 reads 0 closer than its minimum range): as it came
        return rgb.copy(), depth_mm.copy()
    target = vn[inside] * w + un[inside]
    order = np.lexsort((points[src, 2], target))  # by pixel, nearest first
    first = np.r_[True, target[order][1:] != target[order][:-1]]
    win = order[first]
    out_depth = np.zeros(h * w, dtype=np.float64)
    out_rgb = np.zeros((h * w, 3), dtype=np.uint8)
    out_depth[target[win]] = points[src[win], 2]
    out_rgb[target[win]] = rgb[v[src[win]], u[src[win]]]
    hole = np.ones(h * w, dtype=bool)
    hole[target[win]] = False
    nearest = ndimage.distance_transform_edt(hole.reshape(h, w), return_distances=False, return_indices=True)
    flat = (nearest[0] * w + nearest[1]).ravel()
    out_depth, out_rgb = out_depth[flat], out_rgb[flat]
    depth_out = np.clip(np.rint(out_depth), 0, np.iinfo(np.int16).max).astype(depth_mm.dtype)
    return out_rgb.reshape(h, w, 3), depth_out.reshape(depth_mm.shape)


def overlay_own_view(
    rgb: np.ndarray, depth_mm: np.ndarray, own: tuple[np.ndarray, np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """``rgb``/``depth_mm`` with the robot's own links drawn in where they are nearer than what the frame shows.

    ``own``: (rgb, depth mm, mask) of the trained mount's view of the robot alone, as its model renders it at
    the joints the robot reports. The fingers sit 1-3 cm from the lens: a centimetre of mount offset moves them
    half the image, so what the offset camera saw of them cannot be reprojected into where the trained
    camera sees them (the far scene can); the robot's own geometry is known, so it is drawn instead."""
    own_rgb, own_depth, mask = own
    own_d = own_depth[..., 0] if own_depth.ndim == 3 else own_depth
    d = depth_mm[..., 0] if depth_mm.ndim == 3 else depth_mm
    take = mask & (own_d > 0) & ((own_d <= d) | (d == 0))
    rgb, depth_mm = rgb.copy(), depth_mm.copy()
    rgb[take] = own_rgb[take]
    (depth_mm[..., 0] if depth_mm.ndim == 3 else depth_mm)[take] = own_d[take]
    return rgb, depth_mm


class MountCorrectedCamera:
    """``camera`` (``RealSenseCamera``, ``TwinCamera``, anything with ``start``/``stop``/``read``) on a mount
    ``mount`` off the trained one (``camera_pos=x;y;z,camera_rot=a;b;c``, as hand-eye calibration measured it):
    every frame :func:`reproject_to_mount`-ed to the trained mount, then the robot's own links drawn in
    (:func:`overlay_own_view`) from ``robot_view`` (``IRB120RealAgent.own_view``; None: not drawn). The residual
    is the calibration's error."""

    def __init__(self, camera, mount: str, fov_deg: float = SIM_FOV_DEG, robot_view=None):
        self.camera, self.mount = camera, mount
        self.pos, self.rot_deg = parse_mount(mount)
        self.fov_deg = fov_deg
        self.robot_view = robot_view

    def start(self) -> None:
        self.camera.start()

    def stop(self) -> None:
        self.camera.stop()

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        rgb, depth = self.camera.read()
        if depth.shape[0] != depth.shape[1]:
            raise ValueError(f"mount correction expects the sim camera's square frame, got {depth.shape}")
        # the twin knows its camera's intrinsics; a real camera's frame has the sim's (to_sim_frame's crop)
        params = self.camera.params() if hasattr(self.camera, "params") else None
        k = params["intrinsic_cv"][0].cpu().numpy() if params else sim_intrinsics(depth.shape[1], self.fov_deg)
        rgb, depth = reproject_to_mount(rgb, depth, self.pos, self.rot_deg, k)
        return overlay_own_view(rgb, depth, self.robot_view()) if self.robot_view is not None else (rgb, depth)
