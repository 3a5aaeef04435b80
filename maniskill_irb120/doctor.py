"""``maniskill-irb120 doctor``: what a user runs when rendering fails.

It does not trust the driver list alone: it renders one 84x84 RGB-D frame with SAPIEN, which is
exactly what the env's hand camera needs, and reports the device that did it.
"""

from __future__ import annotations

import importlib.metadata as md
import platform
import re
import time

FIX_HINT = (
    "No usable Vulkan device. On Debian 12 (root): add the bookworm-backports suite and run "
    "'apt-get install -t bookworm-backports mesa-vulkan-drivers libvulkan1' (Mesa >= 24.3; "
    "Debian 12's own Mesa 22.3 lacks VK_KHR_external_semaphore_fd, which SAPIEN needs). "
    "On other systems install a Vulkan driver (NVIDIA driver, or Mesa lavapipe >= 24.3) and the "
    "Vulkan loader (libvulkan1). Or run state-only with render_backend='none'."
)


def _devices(summary: str) -> list[dict]:
    devices = []
    for block in re.split(r"\n(?=\S)", summary.strip()):
        head = re.match(r"(\w+):\s*(.*)", block)
        if not head:
            continue
        fields = dict(re.findall(r"^\s+(\w+):?\s+(-?\w+)", block, flags=re.M))
        name = head.group(2)
        devices.append(
            dict(
                kind=head.group(1),
                name=name,
                supported=fields.get("Supported") == "1",
                cpu=any(s in name.lower() for s in ("llvmpipe", "lavapipe", "swiftshader")),
                cuda_id=int(fields.get("cudaId", -1)),
            )
        )
    return devices


def _render_probe() -> dict:
    """Render one 84x84 RGB-D frame of a box; returns timing and whether depth makes sense."""
    import numpy as np
    import sapien

    # explicit systems: a bare sapien.Scene() fails once ManiSkill has set up its own render device
    scene = sapien.Scene([sapien.physx.PhysxCpuSystem(), sapien.render.RenderSystem()])
    scene.set_ambient_light([0.5, 0.5, 0.5])
    builder = scene.create_actor_builder()
    builder.add_box_visual(half_size=[0.1, 0.1, 0.1], material=[1, 0, 0])
    builder.build_static().set_pose(sapien.Pose([0.5, 0, 0]))
    cam = scene.add_camera("probe", 84, 84, 1.57, 0.001, 2.0)
    t0 = time.perf_counter()
    scene.update_render()
    cam.take_picture()
    names = cam.get_picture_names()  # depends on the active shader ("default" vs ManiSkill's "minimal")
    rgb = cam.get_picture("Color")
    pos = cam.get_picture("Position" if "Position" in names else "PositionSegmentation")
    dt = time.perf_counter() - t0
    depth = -float(pos[42, 42, 2])
    if np.issubdtype(pos.dtype, np.integer):  # the minimal shader stores millimetres
        depth /= 1000.0
    return dict(
        ok=bool(rgb[42, 42, 0] > 0.5 and abs(depth - 0.4) < 0.01),
        first_frame_s=round(dt, 3),
        centre_depth_m=round(float(depth), 4),
    )


def diagnose() -> dict:
    report: dict = dict(python=platform.python_version(), platform=platform.platform())
    for pkg in ("maniskill-irb120", "mani-skill", "sapien", "torch", "gymnasium", "xacro"):
        try:
            report[f"version_{pkg}"] = md.version(pkg)
        except md.PackageNotFoundError:
            report[f"version_{pkg}"] = None
    import torch

    report["torch_cuda"] = torch.cuda.is_available()
    report["cuda_sim_available"] = False
    try:
        import sapien

        report["devices"] = _devices(sapien.render.get_device_summary())
    except Exception as e:  # noqa: BLE001 - any failure here is the diagnosis
        report["devices"] = []
        report["device_error"] = repr(e)
    if report["torch_cuda"]:
        try:
            import sapien

            sapien.physx.enable_gpu()
            report["cuda_sim_available"] = True
        except Exception as e:  # noqa: BLE001
            report["cuda_sim_error"] = repr(e)
    usable = [d for d in report["devices"] if d["supported"]]
    report["render_device"] = usable[0] if usable else None
    report["render_probe"] = None
    if usable:
        try:
            report["render_probe"] = _render_probe()
        except Exception as e:  # noqa: BLE001
            report["render_probe"] = dict(ok=False, error=repr(e))
    report["render_ok"] = bool(report["render_probe"] and report["render_probe"]["ok"])
    return report


def format_report(r: dict) -> str:
    lines = ["maniskill-irb120 doctor", f"  python {r['python']} on {r['platform']}"]
    for k, v in r.items():
        if k.startswith("version_"):
            lines.append(f"  {k[8:]:<18} {v or 'NOT INSTALLED'}")
    for d in r["devices"]:
        kind = "CPU (software)" if d["cpu"] else "GPU"
        lines.append(f"  vulkan device      {d['name']} [{kind}] supported={d['supported']}")
    if not r["devices"]:
        lines.append(f"  vulkan device      none found {r.get('device_error', '')}")
    if r["render_probe"]:
        lines.append(f"  render probe       {r['render_probe']}")
    lines.append(f"  torch CUDA         {r['torch_cuda']}")
    lines.append(f"  CUDA sim (physx)   {r['cuda_sim_available']}")
    if r["render_ok"]:
        dev = r["render_device"]
        where = "CPU (lavapipe/llvmpipe: fine for num_envs=1 and process-parallel envs)" if dev["cpu"] else "GPU"
        lines.append(
            f"VERDICT: OK - rendering works on {dev['name']} [{where}]"
            + ("; GPU-batched sim available" if r["cuda_sim_available"] else "; GPU-batched sim not available")
        )
    else:
        lines.append("VERDICT: FAIL - " + FIX_HINT)
    return "\n".join(lines)


def main(json_output: bool = False) -> int:
    """Diagnose rendering and simulation support; exit code 0 when rendering works."""
    import json

    r = diagnose()
    print(json.dumps(r, indent=2) if json_output else format_report(r))
    return 0 if r["render_ok"] else 1
