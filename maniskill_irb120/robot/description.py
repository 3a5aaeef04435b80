"""Robot description: our own low-polygon meshes and the URDF built from the xacro sources.

Triangle count is the cost of CPU (lavapipe) rendering, so every visual is a handful of boxes
and 12-sided cylinders written as OBJ+MTL. Meshes and URDF are generated on first use into a
cache directory keyed by a hash of the xacro sources and of this generator, so an installed,
read-only package works and a change to either source rebuilds everything.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import xml.etree.ElementTree as ET
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

ROBOT_NAME = "irb120_metalwork"
XACRO_MAIN = "irb120_metalwork.urdf.xacro"

Color = tuple[float, float, float]
ORANGE: Color = (0.93, 0.40, 0.05)
GRAPHITE: Color = (0.17, 0.17, 0.19)
ALUMINIUM: Color = (0.66, 0.67, 0.70)
RUBBER: Color = (0.04, 0.04, 0.04)
MATERIALS = {"orange": ORANGE, "graphite": GRAPHITE, "aluminium": ALUMINIUM, "rubber": RUBBER}
CYLINDER_SEGMENTS = 12


def xacro_dir() -> Path:
    """Directory of the xacro sources (the top-level ``assets/`` folder, shipped as package data)."""
    return Path(str(resources.files("maniskill_irb120.assets").joinpath(ROBOT_NAME)))


@lru_cache(maxsize=1)
def geometry() -> dict[str, float]:
    """Plain numeric properties of geometry.xacro, so Python and URDF share one source of truth."""
    ns = "{http://ros.org/wiki/xacro}property"
    out: dict[str, float] = {}
    for prop in ET.parse(xacro_dir() / "geometry.xacro").getroot().iter(ns):
        try:
            out[prop.get("name")] = float(prop.get("value"))
        except (TypeError, ValueError):
            continue
    return out


# --------------------------------------------------------------------------- mesh primitives
def _box(size, center) -> tuple[np.ndarray, np.ndarray]:
    sx, sy, sz = np.asarray(size, dtype=float) / 2
    v = np.array([[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)]) + center
    f = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ]
    )
    return v, f


def _cylinder(radius: float, length: float, axis: str, center, n: int = CYLINDER_SEGMENTS):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.cos(a) * radius, np.sin(a) * radius], 1)
    h = length / 2
    local = np.concatenate([np.c_[ring, np.full(n, -h)], np.c_[ring, np.full(n, h)]])
    perm = {"x": [2, 0, 1], "y": [1, 2, 0], "z": [0, 1, 2]}[axis]
    v = local[:, perm] + np.asarray(center, dtype=float)
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces += [[i, j, n + j], [i, n + j, n + i]]
    for i in range(1, n - 1):
        faces += [[0, i + 1, i], [n, n + i, n + i + 1]]
    f = np.array(faces)
    if axis == "y":  # the (y, z, x) permutation is a reflection: flip winding
        f = f[:, [0, 2, 1]]
    return v, f


def _visual_parts() -> dict[str, list[tuple[str, tuple]]]:
    """Per-link visual parts in the link frame: (material, (kind, args...))."""
    g = geometry()
    x0, x1 = g["finger_x0"], g["finger_x1"]
    half, th, w = g["finger_closed_half_gap"], g["finger_thickness"], g["finger_width"]
    fx, fl = (x0 + x1) / 2, x1 - x0

    def finger(side: int):
        body_y = side * (half + 0.001 + (th - 0.001) / 2)
        pad_y = side * (half + 0.0005)
        return [
            ("aluminium", ("box", (fl, th - 0.001, w), (fx, body_y, 0))),
            ("rubber", ("box", (0.020, 0.001, w), (x1 - 0.010, pad_y, 0))),
        ]

    return {
        "base_link": [
            ("orange", ("box", (0.18, 0.18, 0.09), (-0.01, 0, 0.045))),
            ("graphite", ("cyl", 0.08, 0.076, "z", (0, 0, 0.128))),
            ("graphite", ("box", (0.04, 0.10, 0.05), (-0.115, 0, 0.04))),
        ],
        "link1": [
            ("orange", ("cyl", 0.075, 0.07, "z", (0, 0, 0.035))),
            ("orange", ("cyl", 0.06, 0.14, "y", (0, 0, 0.124))),
            ("graphite", ("cyl", 0.045, 0.02, "y", (0, 0.08, 0.124))),
        ],
        "link2": [
            ("orange", ("box", (0.075, 0.06, 0.27), (0, -0.1, 0.135))),
            ("graphite", ("cyl", 0.05, 0.065, "y", (0, -0.1, 0))),
            ("orange", ("cyl", 0.045, 0.065, "y", (0, -0.1, 0.27))),
        ],
        "link3": [
            ("orange", ("cyl", 0.055, 0.14, "y", (0, 0, 0))),
            ("orange", ("box", (0.09, 0.10, 0.07), (0.02, 0, 0.035))),
            ("graphite", ("cyl", 0.045, 0.15, "x", (0.075, 0, 0.0706))),
        ],
        "link4": [
            ("orange", ("cyl", 0.035, 0.10, "x", (0.05, 0, 0))),
            ("orange", ("box", (0.07, 0.016, 0.05), (0.125, 0.04, 0))),
            ("orange", ("box", (0.07, 0.016, 0.05), (0.125, -0.04, 0))),
        ],
        "link5": [
            ("graphite", ("cyl", 0.03, 0.064, "y", (0, 0, 0))),
            ("orange", ("cyl", 0.028, 0.064, "x", (0.032, 0, 0))),
        ],
        "link6": [("graphite", ("cyl", 0.02, 0.008, "x", (-0.004, 0, 0)))],
        "gripper_base": [
            ("aluminium", ("cyl", 0.025, 0.008, "x", (0.004, 0, 0))),
            ("aluminium", ("box", (0.018, 0.064, 0.030), (0.017, 0, 0))),
            ("rubber", ("box", (0.016, 0.026, 0.014), (0.019, 0, 0.022))),
        ],
        "finger_left": finger(1),
        "finger_right": finger(-1),
    }


def _write_obj(path: Path, parts) -> int:
    """Write one link's OBJ+MTL; returns its triangle count."""
    lines = [f"mtllib {path.stem}.mtl"]
    offset, tris = 1, 0
    for material, (kind, *args) in parts:
        v, f = _box(*args) if kind == "box" else _cylinder(*args)
        lines.append(f"usemtl {material}")
        lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in v]
        lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in f]
        offset += len(v)
        tris += len(f)
    path.write_text("\n".join(lines) + "\n")
    mtl = []
    for name in sorted({m for m, _ in parts}):
        r, gr, b = MATERIALS[name]
        mtl += [f"newmtl {name}", f"Kd {r} {gr} {b}", "Ka 0 0 0", "Ks 0.1 0.1 0.1", "Ns 20", "d 1", ""]
    path.with_suffix(".mtl").write_text("\n".join(mtl))
    return tris


def write_meshes(mesh_dir: Path) -> dict[str, int]:
    mesh_dir.mkdir(parents=True, exist_ok=True)
    return {link: _write_obj(mesh_dir / f"{link}.obj", parts) for link, parts in _visual_parts().items()}


def triangle_count() -> int:
    """Triangles of the whole robot's visual meshes (the CPU-rendering cost)."""
    total = 0
    for parts in _visual_parts().values():
        for _, (kind, *args) in parts:
            total += len((_box(*args) if kind == "box" else _cylinder(*args))[1])
    return total


def xacro_to_urdf(mesh_dir: Path) -> str:
    """Run the xacro package on our sources; mesh paths become absolute so the URDF can live anywhere."""
    import xacro

    doc = xacro.process_file(str(xacro_dir() / XACRO_MAIN), mappings={"mesh_dir": str(mesh_dir)})
    # xacro's banner names the absolute source path; the cache is keyed by content, so drop it
    for node in list(doc.childNodes):
        if node.nodeType == node.COMMENT_NODE and (
            "xacro" in node.data or "EDITING" in node.data or set(node.data.strip()) <= {"="}
        ):
            doc.removeChild(node)
    doc.insertBefore(
        doc.createComment(f" generated by maniskill_irb120 from {XACRO_MAIN}; edit the xacro "), doc.firstChild
    )
    return doc.toprettyxml(indent="  ")


def _source_hash() -> str:
    h = hashlib.sha256()
    for p in sorted(xacro_dir().glob("*.xacro")):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    h.update(Path(__file__).read_bytes())
    return h.hexdigest()[:12]


def cache_root() -> Path:
    env = os.environ.get("MANISKILL_IRB120_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "maniskill_irb120"


TEXTURE_TILE_M = 0.1  # one repeat of a surface texture (envs/appearance.py) per 10 cm


def merged_box_mesh(boxes: list[tuple[tuple, tuple]]) -> str:
    """OBJ file (cached, content-addressed) of several (half_size, centre) boxes as one flat-shaded mesh.

    A static body built from N box visuals is N draw calls; on the CPU rasteriser each costs ~20-30 us
    per 84x84 frame whatever its size, so a tray drawn as one mesh saves four of five.
    """
    lines = []
    normals = [(-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, -1), (0, 0, 1)]
    lines += [f"vn {x} {y} {z}" for x, y, z in normals]
    n_v = 0
    for half, centre in boxes:
        h, c = np.asarray(half, dtype=float), np.asarray(centre, dtype=float)
        for axis in range(3):
            for side in (-1, 1):
                # the face's four corners, counter-clockwise seen from outside
                u, v = (axis + 1) % 3, (axis + 2) % 3
                corners = []
                for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                    p = np.zeros(3)
                    p[axis], p[u], p[v] = side, du, dv * side
                    corners.append(c + p * h)
                lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in corners]
                # planar texture coordinates: the face's two in-plane axes in tiles of TEXTURE_TILE_M
                lines += [f"vt {q[u] / TEXTURE_TILE_M:.6f} {q[v] / TEXTURE_TILE_M:.6f}" for q in corners]
                vn = 2 * axis + (side > 0) + 1
                a = n_v + 1
                lines += [f"f {a}/{a}/{vn} {a + 1}/{a + 1}/{vn} {a + 2}/{a + 2}/{vn}"]
                lines += [f"f {a}/{a}/{vn} {a + 2}/{a + 2}/{vn} {a + 3}/{a + 3}/{vn}"]
                n_v += 4
    text = "\n".join(lines) + "\n"
    path = cache_root() / "scene_meshes" / f"boxes-{hashlib.sha256(text.encode()).hexdigest()[:16]}.obj"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(text)
        os.replace(tmp, path)  # atomic: worker processes may race to write the same file
    return str(path)


def build_description(out_dir: Path, final_dir: Path | None = None) -> Path:
    """Generate meshes and URDF into ``out_dir``; the URDF names meshes under ``final_dir`` (default out_dir)."""
    write_meshes(out_dir / "meshes")
    urdf = out_dir / f"{ROBOT_NAME}.urdf"
    urdf.write_text(xacro_to_urdf((Path(final_dir or out_dir) / "meshes").resolve()))
    return urdf


@lru_cache(maxsize=1)
def urdf_path() -> str:
    """Path of the cached URDF, building it (atomically, safe across worker processes) if missing."""
    final = cache_root() / f"{ROBOT_NAME}-{_source_hash()}"
    urdf = final / f"{ROBOT_NAME}.urdf"
    if not urdf.exists():
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".build-", dir=final.parent))
        try:
            build_description(tmp, final_dir=final)
            try:
                os.rename(tmp, final)
            except OSError:  # another process won the race; its result is identical
                if not urdf.exists():
                    raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return str(urdf)
