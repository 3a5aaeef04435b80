"""The shared scene of the IRB 120 table tasks: table, two trays, floor, graspable objects, contacts.

The robot root stands on the table top at the world origin (world z = 0 = table top); the yellow source
tray and the green destination tray sit in front of it (+x) at (0.35, +0.13) and (0.35, -0.13), 16 x 16 cm
inside, which the IRB 120 reaches everywhere with the gripper pointing down (tested with the IK).

Rendering cost shapes the builders: each static body is one merged mesh (one draw call), the ground is a
flat quad rather than ManiSkill's textured grid, and the big background surfaces are built last so most of
their pixels fail the CPU rasteriser's early depth test (build order is draw order).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import sapien
import torch
from mani_skill.envs.scene import ManiSkillScene
from mani_skill.utils.structs.actor import Actor
from mani_skill.utils.structs.link import Link

from maniskill_irb120.errors import UsageError, nearest
from maniskill_irb120.robot.description import merged_box_mesh

# --------------------------------------------------------------------------- geometry (metres)
TABLE_SIZE = (1.2, 1.0, 0.75)  # x, y, height; the top is at world z = 0
TABLE_CENTER_XY = (0.3, 0.0)  # reaches 0.3 m behind the robot root so the base stands on it
TRAY_INNER = 0.16  # inner side length of both (square) trays
TRAY_WALL_T = 0.005  # wall and floor thickness
TRAY_WALL_H = 0.03  # wall height above the tray floor's top surface
SOURCE_TRAY_XY = (0.35, 0.13)
DEST_TRAY_XY = (0.35, -0.13)
TRAY_FLOOR_TOP = TRAY_WALL_T  # trays stand on the table (z = 0)
SPAWN_MARGIN = 0.03  # object centre keeps this distance from the inner walls
CONTACT_FORCE_EPS = 1e-2  # N; a robot link pressing on the scene harder than this is a collision

OBJECT_SHAPES = ("cube", "cylinder", "random")
OBJECT_HALF_SIZE_RANGE = (0.003, 0.012)  # the open gripper's 26 mm gap; the 2 mm closed gap squeezes >= 6 mm
SOURCE_COLOR, DEST_COLOR = [0.95, 0.8, 0.1, 1.0], [0.1, 0.7, 0.2, 1.0]
# a cylinder stands on its flat face: SAPIEN's cylinder axis is x, turned to z
UPRIGHT = sapien.Pose(q=[math.cos(-math.pi / 4), 0.0, math.sin(-math.pi / 4), 0.0])


def check_object_params(shape: str, half_size: float, mass: float, friction: float) -> None:
    if shape not in OBJECT_SHAPES:
        raise UsageError(f"object_shape={shape!r} is not one of {OBJECT_SHAPES}{nearest(shape, OBJECT_SHAPES)}")
    lo, hi = OBJECT_HALF_SIZE_RANGE
    if not lo <= half_size <= hi:
        raise ValueError(
            f"object_half_size={half_size} m: the open gripper (26 mm gap) holds objects of half size "
            f"{lo * 1000:.0f}..{hi * 1000:.0f} mm (cube half side, cylinder radius and half height)"
        )
    if mass <= 0 or friction < 0:
        raise ValueError(f"object_mass={mass} must be > 0 and object_friction={friction} >= 0")


def _build(scene: ManiSkillScene, make, name: str, static: bool, own_materials: bool) -> Actor:
    """``make(env)`` returns a fresh builder. Built once for all envs, the envs share the builder's render
    materials; with ``own_materials``, once per env (ManiSkill's per-env build, ``set_scene_idxs``) and merged,
    so appearance randomisation can give each env its own colours and textures."""
    if not own_materials:
        builder = make(0)
        return builder.build_static(name=name) if static else builder.build(name=name)
    parts = []
    for i in range(scene.num_envs):
        builder = make(i)
        builder.set_scene_idxs([i])
        parts.append(builder.build_static(name=f"{name}_{i}") if static else builder.build(name=f"{name}_{i}"))
    return Actor.merge(parts, name=name)


def build_box_actor(
    scene: ManiSkillScene, name: str, boxes: list[tuple[tuple, tuple]], color, xy=(0.0, 0.0), own_materials=False
) -> Actor:
    """A static actor of (half_size, centre) boxes: box collisions, one merged visual mesh."""

    def make(_env: int):
        builder = scene.create_actor_builder()
        for half, centre in boxes:
            builder.add_box_collision(pose=sapien.Pose(p=list(centre)), half_size=list(half))
        builder.add_visual_from_file(merged_box_mesh(boxes), material=sapien.render.RenderMaterial(base_color=color))
        builder.initial_pose = sapien.Pose(p=[xy[0], xy[1], 0.0])
        return builder

    return _build(scene, make, name, True, own_materials)


def build_tray(scene: ManiSkillScene, name: str, xy, color, own_materials: bool = False) -> Actor:
    """Open box: floor + 4 walls resting on the table, inner size TRAY_INNER²."""
    t, h, a = TRAY_WALL_T, TRAY_WALL_H, TRAY_INNER / 2
    wall_z, outer = t + h / 2, a + t
    boxes = [
        ((outer, outer, t / 2), (0.0, 0.0, t / 2)),  # floor
        ((t / 2, outer, h / 2), (a + t / 2, 0.0, wall_z)),  # +x wall
        ((t / 2, outer, h / 2), (-a - t / 2, 0.0, wall_z)),  # -x wall
        ((a, t / 2, h / 2), (0.0, a + t / 2, wall_z)),  # +y wall
        ((a, t / 2, h / 2), (0.0, -a - t / 2, wall_z)),  # -y wall
    ]
    return build_box_actor(scene, name, boxes, color, xy, own_materials)


def build_floor(scene: ManiSkillScene, altitude: float, half_width: float = 4.0, own_materials=False) -> Actor:
    """A collision plane with one flat-coloured quad: ManiSkill's ``build_ground`` draws a textured grid
    that costs ~0.7 ms per 84x84 frame on the CPU rasteriser, a third of the render."""

    def make(_env: int):
        builder = scene.create_actor_builder()
        builder.add_plane_collision(sapien.Pose(p=[0, 0, altitude], q=[0.7071068, 0, -0.7071068, 0]))
        builder.add_box_visual(
            pose=sapien.Pose(p=[0, 0, altitude - 0.005]),
            half_size=[half_width, half_width, 0.005],
            material=sapien.render.RenderMaterial(base_color=[0.45, 0.47, 0.5, 1.0]),
        )
        builder.initial_pose = sapien.Pose()
        return builder

    return _build(scene, make, "ground", True, own_materials)


def build_object(
    scene: ManiSkillScene,
    name: str,
    shapes: list[str],
    half_size: float,
    mass: float,
    friction: float,
    color,
    own_materials: bool = False,
) -> Actor:
    """A graspable rigid body per env: ``shapes[i]`` ("cube" or "cylinder") in env i, merged into one
    batched actor. Cubes of side 2·``half_size``; cylinders of radius and half height ``half_size``,
    standing. Either has mass ``mass`` and ``friction`` on its surface."""
    mat = sapien.pysapien.physx.PhysxMaterial(static_friction=friction, dynamic_friction=friction, restitution=0.0)
    h = half_size

    def make(shape: str):
        render_mat = sapien.render.RenderMaterial(base_color=color)
        builder = scene.create_actor_builder()
        if shape == "cube":
            builder.add_box_collision(half_size=[h] * 3, material=mat, density=mass / (2 * h) ** 3)
            builder.add_box_visual(half_size=[h] * 3, material=render_mat)
        else:
            builder.add_cylinder_collision(
                pose=UPRIGHT, radius=h, half_length=h, material=mat, density=mass / (math.pi * h * h * 2 * h)
            )
            builder.add_cylinder_visual(pose=UPRIGHT, radius=h, half_length=h, material=render_mat)
        builder.initial_pose = sapien.Pose(p=[*SOURCE_TRAY_XY, TRAY_FLOOR_TOP + h])
        return builder

    if own_materials:
        return _build(scene, lambda i: make(shapes[i]), name, False, True)
    if len(set(shapes)) == 1:
        return make(shapes[0]).build(name=name)
    parts = []
    for shape in sorted(set(shapes)):
        builder = make(shape)
        builder.set_scene_idxs([i for i, s in enumerate(shapes) if s == shape])
        parts.append(builder.build(name=f"{name}_{shape}"))
    return Actor.merge(parts, name=name)


class TableScene:
    """Builds the shared scene (trays first, table and floor last: see the module docstring)."""

    def __init__(self, scene: ManiSkillScene, own_materials: bool = False):
        """``own_materials``: each env's surfaces get materials of their own (appearance randomisation)."""
        self.scene, self.own_materials = scene, own_materials

    def build_trays(self) -> None:
        own = self.own_materials
        self.source_tray = build_tray(self.scene, "source_tray", SOURCE_TRAY_XY, SOURCE_COLOR, own)
        self.dest_tray = build_tray(self.scene, "dest_tray", DEST_TRAY_XY, DEST_COLOR, own)

    def build_background(self) -> None:
        sx, sy, sz = TABLE_SIZE
        self.table = build_box_actor(
            self.scene,
            "table",
            [((sx / 2, sy / 2, sz / 2), (TABLE_CENTER_XY[0], TABLE_CENTER_XY[1], -sz / 2))],
            [0.55, 0.42, 0.3, 1.0],
            own_materials=self.own_materials,
        )
        self.ground = build_floor(self.scene, altitude=-sz, own_materials=self.own_materials)

    @property
    def actors(self) -> list[Actor]:
        return [self.table, self.source_tray, self.dest_tray, self.ground]


# the kinds of body :meth:`Contacts.scan` tells apart, as bits: a contact's pair of kinds is their OR
_SCENE, _ROBOT, _FINGER, _OBJ = 1, 2, 4, 8


class ContactFlags(NamedTuple):
    """One step's contacts (a touch is a force above CONTACT_FORCE_EPS); object j is the j-th watched object."""

    robot_hit: torch.Tensor
    """(N,) a robot link (base excluded) touches the scene"""
    object_hit: torch.Tensor
    """(M, N) object j touches the scene"""
    finger_forces: torch.Tensor
    """(M, 2, N, 3) force on finger k from object j"""


class Contacts:
    """The contacts a table task watches, batched: robot links (base excluded: it stands on the table)
    against the scene, each object against the scene, and each finger against each object.

    GPU: one contact-impulse query for every pair and env, built on first use (one synchronisation per
    step instead of one per pair). CPU: one pass over PhysX's contact list (:meth:`scan`); the per-pair
    queries (:meth:`pairwise`) are the reference it is tested against.
    """

    def __init__(
        self,
        scene: ManiSkillScene,
        robot_links: list[Link],
        fingers: list[Link],
        scene_actors: list[Actor],
        objects: list[Actor],
    ):
        self.scene, self.objects, self.n_scene = scene, objects, len(scene_actors)
        self.robot_links, self.fingers, self.scene_actors = robot_links, fingers, scene_actors
        touching = [link for link in robot_links if len(link._bodies[0].get_collision_shapes()) > 0]
        self.n_robot = len(touching) * len(scene_actors)
        self.pairs = (
            [(link, a) for a in scene_actors for link in touching]
            + [(o, a) for o in objects for a in scene_actors]
            + [(f, o) for o in objects for f in fingers]
        )
        self._query = None
        self._kind = None
        self._last: ContactFlags | None = None  # what flags() last returned
        self._frozen = False  # a restored state's contacts stand in for PhysX's until the next physics step

    def impulses(self) -> torch.Tensor:
        """(P, N, 3) impulses of :attr:`pairs`: one batched query on the GPU, per-pair queries on the CPU."""
        if not self.scene.gpu_sim_enabled:
            return torch.stack([self.scene.get_pairwise_contact_impulses(a, b) for a, b in self.pairs])
        px = self.scene.px
        if self._query is None:
            self._query = px.gpu_create_contact_pair_impulse_query(
                [bp for a, b in self.pairs for bp in zip(a._bodies, b._bodies)]
            )
        px.gpu_query_contact_pair_impulses(self._query)
        # rows are pair-major (each pair's N envs in a row), as the body pairs were listed
        return self._query.cuda_impulses.torch().clone().view(len(self.pairs), self.scene.num_envs, 3)

    def flags(self) -> ContactFlags:
        """This step's :class:`ContactFlags`; after :meth:`restore`, the restored ones until :meth:`stepped`."""
        if not self._frozen or self._last is None:
            self._last = self.pairwise() if self.scene.gpu_sim_enabled else self.scan()
        return self._last

    # A state restore moves the bodies but not PhysX's contact list, which stays the last simulated step's: the
    # contacts a restored state was evaluated with travel in the env state (IRB120TableEnv.get_state_dict).

    def state(self) -> dict[str, torch.Tensor]:
        """The contacts last returned by :meth:`flags` as ``(N, D)`` float rows (an env state's layout)."""
        f = self._last if self._last is not None else self.flags()
        n = f.robot_hit.shape[0]
        return dict(
            robot_hit=f.robot_hit.float()[:, None],
            object_hit=f.object_hit.float().T.contiguous(),
            finger_forces=f.finger_forces.permute(2, 0, 1, 3).reshape(n, -1).float(),
        )

    def restore(self, state: dict[str, torch.Tensor], env_idx: torch.Tensor | None = None) -> None:
        """Serve ``state`` (:meth:`state`'s layout; rows of ``env_idx``, all envs when None) from :meth:`flags` until
        the next physics step. The other envs keep the contacts of their last step, which a restore left alone."""
        cur = self._last if self._last is not None else self.flags()
        m, n = cur.object_hit.shape
        rows = torch.arange(n, device=cur.robot_hit.device) if env_idx is None else torch.as_tensor(env_idx).long()
        robot_hit, object_hit, forces = cur.robot_hit.clone(), cur.object_hit.clone(), cur.finger_forces.clone()
        dev = robot_hit.device
        robot_hit[rows] = state["robot_hit"].to(dev)[:, 0] > 0.5
        object_hit[:, rows] = (state["object_hit"].to(dev) > 0.5).T
        forces[:, :, rows] = state["finger_forces"].to(dev, forces.dtype).reshape(-1, m, 2, 3).permute(1, 2, 0, 3)
        self._last, self._frozen = ContactFlags(robot_hit, object_hit, forces), True

    def stepped(self) -> None:
        """Physics is about to step: :meth:`flags` reads PhysX again."""
        self._frozen = False

    def pairwise(self) -> ContactFlags:
        forces = self.impulses() / self.scene.px.timestep
        hit = torch.linalg.norm(forces, dim=2) > CONTACT_FORCE_EPS  # (P, N)
        m, r, s = len(self.objects), self.n_robot, self.n_scene
        obj_hit = hit[r : r + m * s].view(m, s, -1).any(1)
        return ContactFlags(hit[:r].any(0), obj_hit, forces[r + m * s :].view(m, 2, -1, 3))

    def scan(self) -> ContactFlags:
        """CPU (one env): one pass over PhysX's contact list, same answer as :meth:`pairwise`. A contact's impulse
        (a sum over its points, read from SAPIEN one point at a time) is summed only where it can change the answer:
        always between a finger and an object, between the scene and a body only until that body is known to touch."""
        if self._kind is None:
            kind = {a._bodies[0].entity: (_SCENE, 0) for a in self.scene_actors}
            kind.update({link._bodies[0].entity: (_ROBOT, 0) for link in self.robot_links})
            kind.update({f._bodies[0].entity: (_FINGER, i) for i, f in enumerate(self.fingers)})
            kind.update({o._bodies[0].entity: (_OBJ, j) for j, o in enumerate(self.objects)})
            self._kind = kind
        kind, m = self._kind, len(self.objects)
        dt = self.scene.px.timestep
        eps_sq = (CONTACT_FORCE_EPS * dt) ** 2
        robot_hit, hits = False, np.zeros(m, dtype=bool)
        finger = np.zeros((m, 2, 3))
        for c in self.scene.px.get_contacts():
            bodies = c.bodies
            k0, k1 = kind.get(bodies[0].entity), kind.get(bodies[1].entity)
            if k0 is None or k1 is None:
                continue
            t0, t1 = k0[0], k1[0]
            pair = t0 | t1
            if pair == _FINGER | _OBJ:  # impulse on the finger, ManiSkill's pairwise sign convention
                points = c.points
                impulse = sum(p.impulse for p in points) if points else np.zeros(3)
                if t0 == _OBJ:
                    finger[k0[1], k1[1]] -= impulse
                else:
                    finger[k1[1], k0[1]] += impulse
            elif pair & _SCENE and pair != _SCENE:  # the scene and a body
                other = k1 if t0 == _SCENE else k0
                if other[0] == _OBJ:
                    if hits[other[1]]:
                        continue
                elif robot_hit:
                    continue
                points = c.points
                impulse = sum(p.impulse for p in points) if points else np.zeros(3)
                if float(impulse @ impulse) > eps_sq:
                    if other[0] == _OBJ:
                        hits[other[1]] = True
                    else:
                        robot_hit = True
        dev = self.scene.device
        forces = torch.from_numpy((finger / dt).astype(np.float32))[:, :, None]  # (M, 2, 1, 3)
        robot = torch.from_numpy(np.array([robot_hit]))
        obj = torch.from_numpy(hits[:, None])
        if dev.type != "cpu":
            robot, obj, forces = robot.to(dev), obj.to(dev), forces.to(dev)
        return ContactFlags(robot, obj, forces)
