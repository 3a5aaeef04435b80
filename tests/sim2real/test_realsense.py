"""``RealSenseCamera`` through librealsense itself, with no camera: a ``software_device`` with a depth and a colour
sensor of known intrinsics and depth units is recorded (``rs.recorder``), and the recording drives the camera's
own pipeline (``config.enable_device_from_file``): stream matching, the depth scale and the intrinsics read
from the device, depth aligned to colour, the crop to the sim's field of view, 84x84.

A live ``software_device`` cannot drive ``rs.pipeline`` in pyrealsense2 2.59: ``software_device.add_to(context)``
returns, yet ``context.query_devices()`` lists nothing (any mask) and ``pipeline(context).start()`` raises "No
device connected"; a recording of it plays through the unchanged pipeline.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from maniskill_irb120.sim2real.cameras import RealSenseCamera

rs = pytest.importorskip("pyrealsense2")

W, H = 640, 480
F_DEPTH, F = 385.0, 600.0  # a D435 at 640x480: the depth imager's 385 px, the narrower colour camera's ~600 px
PP = (319.5, 239.5)
FOV = 40.0  # the crop the sim would be trained for (camera_fov=40): the colour camera sees 43.6 deg high
FRAMES = 4


def scene(depth_unit_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A plane at 0.4 m with a box at 0.3 m in the middle, in raw depth units; colour: red grows with the column,
    green with the row."""
    z = np.full((H, W), 0.4)
    z[200:280, 280:360] = 0.3
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 0] = np.round(np.arange(W) * 255 / (W - 1))[None, :]
    rgb[..., 1] = np.round(np.arange(H) * 255 / (H - 1))[:, None]
    rgb[..., 2] = 60
    return np.round(z / depth_unit_m).astype(np.uint16), rgb


def stream(kind, uid: int, fmt, bpp: int, f: float):
    v = rs.video_stream()
    v.type, v.index, v.uid, v.width, v.height, v.fps, v.bpp, v.fmt = kind, 0, uid, W, H, 30, bpp, fmt
    k = rs.intrinsics()
    k.width, k.height, k.fx, k.fy, k.ppx, k.ppy = W, H, f, f, *PP
    k.model, k.coeffs = rs.distortion.none, [0.0] * 5
    v.intrinsics = k
    return v


def record(path, depth_unit_m: float = 0.001, colour: bool = True) -> str:
    """``FRAMES`` framesets of :func:`scene` from a software device, recorded to ``path`` (.db3)."""
    dev = rs.software_device()
    dev.register_info(rs.camera_info.name, "software D435")
    dev.register_info(rs.camera_info.serial_number, "0000")
    depth_sensor = dev.add_sensor("Stereo Module")
    depth_profile = depth_sensor.add_video_stream(stream(rs.stream.depth, 0, rs.format.z16, 2, F_DEPTH), True)
    depth_sensor.add_read_only_option(rs.option.depth_units, depth_unit_m)
    sensors = [(depth_sensor, depth_profile)]
    if colour:
        colour_sensor = dev.add_sensor("RGB Camera")
        colour_profile = colour_sensor.add_video_stream(stream(rs.stream.color, 1, rs.format.rgb8, 3, F), True)
        same_place = rs.extrinsics()
        same_place.rotation, same_place.translation = [1, 0, 0, 0, 1, 0, 0, 0, 1], [0, 0, 0]
        depth_profile.register_extrinsics_to(colour_profile, same_place)
        sensors.append((colour_sensor, colour_profile))
    recorder = rs.recorder(str(path), dev)
    recorded = recorder.query_sensors()
    for s in recorded:
        s.open(s.get_stream_profiles()[0])
        s.start(lambda f: None)
    depth, rgb = scene(depth_unit_m)
    for i in range(FRAMES):
        for (sensor, profile), pixels in zip(sensors, (depth, rgb)):
            f = rs.software_video_frame()
            f.pixels, f.bpp, f.stride = pixels, pixels.itemsize * (3 if pixels.ndim == 3 else 1), pixels[0].nbytes
            f.timestamp, f.domain, f.frame_number = i * 1000 / 30, rs.timestamp_domain.hardware_clock, i
            f.profile = profile.as_video_stream_profile()
            sensor.on_video_frame(f)
    time.sleep(0.1)  # the recorder writes on its own thread
    for s in recorded:
        s.stop()
        s.close()
    del recorder, recorded
    return str(path)


@pytest.fixture(scope="module", params=[0.001, 0.0001], ids=["mm", "100um"])  # D435's and D405's default units
def recording(request, tmp_path_factory):
    return request.param, record(tmp_path_factory.mktemp("rs") / "scene.db3", request.param)


def sim_pixel(u_depth: float, v_depth: float) -> tuple[int, int]:
    """The 84x84 pixel (row, col) that a depth pixel lands in: into the colour camera (same place, focal ``F``),
    then the crop of ``FOV`` around the principal point."""
    half = F * math.tan(math.radians(FOV) / 2)
    u, v = (PP[0] + (u_depth - PP[0]) * F / F_DEPTH, PP[1] + (v_depth - PP[1]) * F / F_DEPTH)
    return int((v - (PP[1] - half)) / (2 * half) * 84), int((u - (PP[0] - half)) / (2 * half) * 84)


def test_a_recording_plays_through_the_camera_pipeline(recording):
    unit, path = recording
    cam = RealSenseCamera(playback=path, fov_deg=FOV)
    cam.start()
    try:
        assert cam.intrinsics == pytest.approx((F, F, *PP))
        assert cam.depth_to_mm == pytest.approx(unit * 1000, rel=1e-6)  # read from the device, not assumed
        rgb, depth = cam.read()
    finally:
        cam.stop()
    assert rgb.shape == (84, 84, 3) and rgb.dtype == np.uint8
    assert depth.shape == (84, 84, 1) and depth.dtype == np.int16
    (r0, c0), (r1, c1) = sim_pixel(280, 200), sim_pixel(360, 280)  # the box's corners: (30, 30), (54, 54)
    box, plane = depth[r0 + 2 : r1 - 1, c0 + 2 : c1 - 1, 0], np.r_[depth[: r0 - 1].ravel(), depth[r1 + 2 :].ravel()]
    # librealsense's align leaves a few holes even on this flat, co-located pair: 0 is "no reading"
    assert set(np.unique(box)) <= {0, 300} and (box == 300).mean() > 0.9
    assert set(np.unique(plane)) <= {0, 400} and (plane == 400).mean() > 0.9
    # colour: each sim pixel's centre ray, area-averaged over a linear gradient, reads the gradient there
    half = F * math.tan(math.radians(FOV) / 2)
    u = PP[0] - half + (np.arange(84) + 0.5) * 2 * half / 84
    v = PP[1] - half + (np.arange(84) + 0.5) * 2 * half / 84
    np.testing.assert_allclose(rgb[40, :, 0], u * 255 / (W - 1), atol=2)
    np.testing.assert_allclose(rgb[:, 40, 1], v * 255 / (H - 1), atol=2)
    assert (rgb[..., 2] == 60).all()


def test_a_camera_narrower_than_the_sim_is_named(recording):
    cam = RealSenseCamera(playback=recording[1], fov_deg=90.0)
    cam.start()
    try:
        with pytest.raises(ValueError, match="less than the sim's 90.0 deg"):  # a D435's colour camera: 69 x 42 deg
            cam.read()
    finally:
        cam.stop()


def test_wrong_streams_and_no_camera_are_named(recording, tmp_path):
    with pytest.raises(RuntimeError, match="no 848x480 rgb8 colour and z16 depth at 30 fps"):
        RealSenseCamera(playback=recording[1], width=848).start()
    depth_only = record(tmp_path / "depth_only.db3", colour=False)
    with pytest.raises(RuntimeError, match="recording .*depth_only.db3: no 640x480 rgb8 colour"):
        RealSenseCamera(playback=depth_only, fov_deg=FOV).start()
    with pytest.raises(RuntimeError, match="RealSense 123456789012: no 640x480 .*no camera connected"):
        RealSenseCamera(serial="123456789012").start()
    with pytest.raises(RuntimeError, match=r"read\(\) before start\(\)"):
        RealSenseCamera().read()


def test_no_more_frames_is_an_error_not_a_hang(recording):
    cam = RealSenseCamera(playback=recording[1], fov_deg=FOV, timeout_ms=300)
    cam.start()
    reads = 0
    try:
        with pytest.raises(RuntimeError, match="no frames within 300 ms"):
            for _ in range(FRAMES + 1):
                cam.read()
                reads += 1
    finally:
        cam.stop()
    assert 1 <= reads <= FRAMES  # the recording's framesets, then the error a stalled camera gives
