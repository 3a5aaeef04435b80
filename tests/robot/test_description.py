"""The robot description build (xacro, generated meshes), packaging and the doctor."""

from __future__ import annotations

import zipfile
from pathlib import Path

import pytest

from maniskill_irb120.robot import description as rd


def test_urdf_regenerates_identically(tmp_path):
    used = Path(rd.urdf_path())
    again = rd.xacro_to_urdf(used.parent / "meshes")
    assert again == used.read_text()
    meshes = rd.write_meshes(tmp_path)
    for link, _ in meshes.items():
        assert (tmp_path / f"{link}.obj").read_text() == (used.parent / "meshes" / f"{link}.obj").read_text()


def test_robot_is_low_poly():
    assert 300 < rd.triangle_count() < 3000


@pytest.mark.slow
def test_wheel_ships_assets(bench, tmp_path):
    import subprocess
    import sys

    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(tmp_path),
            str(bench.REPO),
        ],
        check=True,
    )
    (whl,) = tmp_path.glob("maniskill_irb120-*.whl")
    names = zipfile.ZipFile(whl).namelist()
    for f in ["irb120_metalwork.urdf.xacro", "geometry.xacro", "physics.xacro", "gripper.xacro", "macros.xacro"]:
        assert f"maniskill_irb120/assets/irb120_metalwork/{f}" in names
    for f in ["gbuffer.vert", "gbuffer.frag"]:
        assert f"maniskill_irb120/assets/shaders/rgbd_forward/{f}" in names
    assert "maniskill_irb120/assets/rapid/protocol_vectors.json" in names
    for f in ["IRB120Server.mod", "IRB120Serial.mod", "IRB120Socket.mod", "IRB120Zone.sys"]:
        assert f"maniskill_irb120/assets/rapid/{f}" in names
    for f in ["abb/protocol.py", "abb/emulator/rapid/grammar.lark", "policies/section.py", "experts/pick_place.py"]:
        assert f"maniskill_irb120/{f}" in names


def test_doctor_finds_render_device():
    import json
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-m", "maniskill_irb120.cli", "doctor", "--json"], capture_output=True, text=True, timeout=120
    )
    r = json.loads(out.stdout)
    assert out.returncode == 0, out.stdout + out.stderr
    assert r["render_ok"] and r["render_device"]["supported"], r
    assert r["render_probe"]["centre_depth_m"] == pytest.approx(0.4, abs=0.01)
