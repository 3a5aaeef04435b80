"""Domain randomisation for every IRB 120 task: one set of names for training with randomisation and for the
digital twin's shift (``sim2real-eval --shift``).

Each field is off by default (the env is then bit-identical to one without randomisation), a fixed value, or a
``(low, high)`` range drawn uniformly per env. Draws come from a generator seeded by ManiSkill's per-env
episode seed, so the same seed draws the same values on CPU and GPU, apart from the task's own draws.

| field | unit | drawn | granularity in ManiSkill 3.0.1 |
|---|---|---|---|
| ``camera_pos`` | m, per axis of the mount (x along the approach, z away from the gripper) | each episode | per env |
| ``camera_rot`` | deg, per axis (x, y, z of the camera frame) | each episode | per env |
| ``camera_fov`` | deg (absolute; off: the agent's 90°) | each episode | per env |
| ``light`` | scale of every light's intensity | each episode | per env on the CPU; GPU: env 0's (shared lights) |
| ``color`` | max RGB jitter of the objects, trays, table and floor | each episode | per env (see below) |
| ``object_color`` | max RGB jitter of the objects alone, for them in place of ``color`` | each episode | per env |
| ``texture`` | probability a surface wears a procedural texture (``appearance.py``) | each episode | env, surface |
| ``roughness`` | GGX roughness, 0..1 (off: each material's own) | each episode | env, surface |
| ``specular`` | specular strength, 0..1 (off: each material's own) | each episode | env, surface |
| ``depth_noise`` | std of Gaussian depth noise, mm | each step | per pixel |
| ``depth_dropout`` | probability a depth pixel reads 0 | each step | per pixel |
| ``depth_model`` | a RealSense preset, ``d435`` or ``d405`` (envs/depth_model.py), or choices | each step | per pixel |
| ``object_size`` | scale of ``object_half_size`` | scene build | one draw for all envs |
| ``object_mass`` | scale of ``object_mass`` | scene build | per env |
| ``object_friction`` | scale of ``object_friction`` | scene build | per env |
| ``latency`` | s: how far into a control period new targets reach the drives | each episode | per env, 10 ms steps |
| ``nominal`` | probability an episode draws none of the above (build fields aside) | each episode | per env |

``camera_pos`` and ``camera_rot`` take one range for every axis or one per axis (``a:b;c:d;e:f``). Moved back
(x below about −8 mm) and down (z between about −15 and −5 mm), the lens enters the hand's geometry and up to 86 %
of the image's top half reads under 15 mm, which no real mount error does: a range for training should keep z above
−5 mm (measured on seed 0's start pose, x and z on a grid).

The appearance fields (``color``, ``object_color``, ``texture``, ``roughness``, ``specular``) change materials. On
the CPU an env owns its materials; a GPU-batched scene shares one material per builder between its envs, so with an
appearance field active the scene builds each env's table, trays, floor and objects with materials of their own.

``object_color`` gives the task's objects a jitter of their own, wider than the scene's: a camera policy that finds
its cube by the cube's red loses it when the cube turns as orange as its tray (docs/notes/collision-under-shift.md),
and one trained on cubes of many colours has to find it by its shape and depth. Off, the objects jitter as
``color`` says, and every draw is what it was before the field existed.

``latency`` is what a robot on a fixed clock shows (``sim2real`` with ``step_end="period"``): the arm read mid-move
at the period's end. A deployment whose steps wait for the robot to arrive (the default) shows none of it.

``depth_model`` stands before ``depth_noise``/``depth_dropout`` (which then add to it): range limits, disparity
noise and quantisation, edges, occlusion shadow and dark/specular dropout as a RealSense D435 or D405 measures
them, with the figures and their sources in envs/depth_model.py. ``depth_model=d435|d405|off`` draws one of its
choices per env each episode, after every other field, so the other draws stay as they were.

``nominal`` mixes the unrandomised view into training: with ``nominal=0.3`` three episodes in ten see the nominal
camera, light, surfaces and depth, and the rest draw every range as without it. Under the ranges alone a policy
hardly ever sees the view it is evaluated in with no shift: with each of a task's five surfaces (object, table,
two trays, ground) textured at ``texture=0.7``, a scene with none textured comes about one episode in 400
(0.3⁵), and a continuous range never draws its nominal value exactly. Whether an episode is nominal comes from a
stream of its own, so the other episodes draw the values they would without ``nominal`` (in a batch, the per-pixel
depth noise, one stream seeded from the first reset env's, can differ when that env is nominal).

A range for a scene-build field makes the task rebuild its scene every episode (``reconfiguration_freq=1``,
as ``object_shape="random"``) unless ``reconfiguration_freq`` is given: drawn once, a "randomised" object
size would be one size for a whole training run, and a policy trained so fits that one draw only
(docs/notes/adapter-state-policies.md). ``reconfiguration_freq=0`` keeps one draw per build on purpose.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np
import sapien
import torch

from maniskill_irb120.envs import appearance
from maniskill_irb120.envs.depth_model import DepthModel, drawn, preset

Value = float | tuple[float, ...] | None
VECTOR_FIELDS = ("camera_pos", "camera_rot")
OFF = dict(camera_pos=0.0, camera_rot=0.0, camera_fov=None, light=1.0, color=0.0, depth_noise=0.0, depth_dropout=0.0)
OFF.update(texture=0.0, roughness=None, specular=None, depth_model=None, object_color=None)
OFF.update(object_size=1.0, object_mass=1.0, object_friction=1.0, latency=0.0, nominal=0.0)
SCALES = ("light", "object_size", "object_mass", "object_friction")
BUILD_FIELDS = ("object_size", "object_mass", "object_friction")  # drawn when the scene is built
APPEARANCE_FIELDS = ("color", "texture", "roughness", "specular", "object_color")
UNIT_FIELDS = ("depth_dropout", "texture", "roughness", "specular", "nominal")  # probabilities and 0..1 terms
NONE_FIELDS = ("camera_fov", "roughness", "specular", "object_color")  # None: off (the nominal camera's, each
# material's own, color's)


def _depth_models(v) -> str | tuple[str, ...] | None:
    """``depth_model``'s value: None (off), one preset's name, or a tuple of two or more choices (each a preset's
    name or ``"off"``), one drawn per env each episode; ``"d435|d405|off"`` in a spec."""
    if v is None:
        return None
    names = v.split("|") if isinstance(v, str) else v
    if not isinstance(names, (tuple, list)) or not all(isinstance(n, str) for n in names):
        raise ValueError(f"depth_model={v!r}: a preset name, e.g. 'd435', or choices 'd435|d405|off'")
    out = tuple("off" if n.strip().lower() in ("off", "none", "") else preset(n).name for n in names)
    if len(set(out)) != len(out):
        raise ValueError(f"depth_model={v!r}: a choice names each model once")
    if len(out) == 1:
        return None if out[0] == "off" else out[0]
    return out


@dataclass(frozen=True)
class Randomization:
    camera_pos: Value = 0.0
    camera_rot: Value = 0.0
    camera_fov: Value = None
    light: Value = 1.0
    color: Value = 0.0
    depth_noise: Value = 0.0
    depth_dropout: Value = 0.0
    texture: Value = 0.0
    roughness: Value = None
    specular: Value = None
    depth_model: str | tuple[str, ...] | None = None  # a preset name (envs/depth_model.py PRESETS), or a choice
    object_size: Value = 1.0
    object_mass: Value = 1.0
    object_friction: Value = 1.0
    latency: Value = 0.0
    nominal: Value = 0.0
    object_color: Value = None

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "depth_model":
                object.__setattr__(self, f.name, _depth_models(v))
                continue
            if v is None:
                if f.name not in NONE_FIELDS:
                    raise ValueError(f"{f.name}: None is 'off' only for {', '.join(NONE_FIELDS)}")
                continue
            vals = (float(v),) if np.isscalar(v) else tuple(float(x) for x in v)
            if not all(math.isfinite(x) for x in vals):
                raise ValueError(f"{f.name}={v!r}: not finite")
            if len(vals) in (3, 6) and f.name not in VECTOR_FIELDS or len(vals) not in (1, 2, 3, 6):
                raise ValueError(
                    f"{f.name}={v!r}: a value or a (low, high) range"
                    + (", an x;y;z vector, or a range per axis" if f.name in VECTOR_FIELDS else "")
                )
            if len(vals) in (2, 6) and any(lo > hi for lo, hi in zip(vals[::2], vals[1::2])):
                raise ValueError(f"{f.name}={v!r}: low > high")
            if f.name in SCALES and min(vals) <= 0:
                raise ValueError(f"{f.name}={v!r}: a scale must be > 0")
            if f.name in ("color", "object_color", "depth_noise", "latency") and min(vals) < 0:
                raise ValueError(f"{f.name}={v!r}: must be >= 0")
            if f.name in UNIT_FIELDS and not 0 <= min(vals) <= max(vals) <= 1:
                raise ValueError(f"{f.name}={v!r}: must lie in [0, 1] (a probability, or a material term)")
            if f.name == "nominal" and len(vals) != 1:
                raise ValueError(f"nominal={v!r}: one probability, not a range")
            if f.name == "camera_fov" and not 1 <= min(vals) <= max(vals) < 180:
                raise ValueError(f"{f.name}={v!r}: degrees in [1, 180)")
            object.__setattr__(self, f.name, vals[0] if len(vals) == 1 else vals)

    @classmethod
    def parse(cls, spec: str) -> Randomization:
        """``"camera_fov=80,depth_noise=2,object_mass=0.5:2,camera_pos=0.01;0;0"``: ``a:b`` a range, ``x;y;z``
        a fixed vector, ``a:b;c:d;e:f`` a range per axis (a mount's error need not be alike on every axis)."""
        kw = {}
        names = {f.name for f in fields(cls)}
        for item in filter(None, (p.strip() for p in spec.split(","))):
            name, eq, text = item.partition("=")
            if not eq or name.strip() not in names:
                raise ValueError(f"randomisation {item!r}: use NAME=VALUE with NAME one of {sorted(names)}")
            if name.strip() == "depth_model":
                kw["depth_model"] = text.strip()
                continue
            try:
                parts = [float(x) for x in text.replace(":", ";").split(";")]
            except ValueError:
                raise ValueError(f"randomisation {item!r}: {text!r} is not a number, LOW:HIGH or X;Y;Z") from None
            axes = text.split(";")
            if ":" in text and not all(a.count(":") == 1 for a in axes) or len(axes) not in (1, 3):
                raise ValueError(f"randomisation {item!r}: a range is LOW:HIGH (per axis: LOW:HIGH;LOW:HIGH;LOW:HIGH)")
            kw[name.strip()] = parts[0] if len(parts) == 1 else tuple(parts)
        return cls(**kw)

    @classmethod
    def from_any(cls, spec) -> Randomization:
        if spec is None:
            return cls()
        if isinstance(spec, cls):
            return spec
        if isinstance(spec, str):
            return cls.parse(spec)
        if isinstance(spec, dict):
            unknown = set(spec) - {f.name for f in fields(cls)}
            if unknown:
                raise ValueError(f"unknown randomisation fields {sorted(unknown)}")
            return cls(**spec)
        raise TypeError(f"randomization must be None, a dict, a string or a Randomization, got {type(spec).__name__}")

    def build_ranges(self) -> list[str]:
        """The scene-build fields given as a (low, high) range: one draw per scene build."""
        return [k for k in BUILD_FIELDS if not np.isscalar(getattr(self, k))]

    def active(self) -> list[str]:
        return [f.name for f in fields(self) if getattr(self, f.name) != OFF[f.name]]

    def as_dict(self) -> dict:
        return asdict(self)

    def draw(self, name: str, rng: np.random.Generator, n: int = 1) -> np.ndarray:
        """(n,) or (n, 3) values of ``name`` for n envs (vector fields per axis)."""
        v = getattr(self, name)
        dim = 3 if name in VECTOR_FIELDS else 1
        if np.isscalar(v):
            out = np.full((n, dim), float(v))
        elif len(v) == 3:
            out = np.tile(np.asarray(v, dtype=np.float64), (n, 1))
        elif len(v) == 6:  # (low, high) per axis
            out = rng.uniform(v[0::2], v[1::2], size=(n, dim))
        else:
            out = rng.uniform(v[0], v[1], size=(n, dim))
        return out if dim == 3 else out[:, 0]


_NOMINAL = Randomization()
"""what an episode drawn nominal (``nominal``) draws from: nothing"""


def _rng(env, i: int) -> np.random.Generator:
    """The randomisation stream of env ``i``'s episode: its own, so the task's draws are untouched."""
    seeds = getattr(env, "_episode_seed", None)
    seed = int(seeds[i]) if seeds is not None else 0
    return np.random.default_rng([seed, 0xD0]) if seeds is not None else np.random.default_rng()


def _build_rng(env, i: int):
    """Env ``i``'s RNG at scene build: ManiSkill's per-env episode RNG, as ``object_shape="random"`` uses."""
    rngs = getattr(env, "_batched_episode_rng", None)
    return rngs[i] if rngs is not None else np.random.default_rng()


def _euler_quat(deg: np.ndarray) -> list[float]:
    q = sapien.Pose()
    for axis, a in zip(np.eye(3), np.radians(deg)):
        q = q * sapien.Pose(q=[math.cos(a / 2), *(math.sin(a / 2) * axis)])
    return list(q.q)


def camera_mount_offset(pos, rot_deg) -> sapien.Pose:
    """The hand camera's pose in the frame of its nominal mount after a ``camera_pos``/``camera_rot`` value: the
    translation (m, in the mount's axes, which are the nominal camera's: x along the view, y left, z up), then
    rotations about the camera's x, y and z axes (deg), in that order. The sim moves its camera by it; sim2real's
    mount correction (``sim2real/cameras.py``) undoes a measured one, so both read the same convention here."""
    return sapien.Pose(p=[float(x) for x in np.asarray(pos, dtype=np.float64)], q=_euler_quat(np.asarray(rot_deg)))


class RandomizationMixin:
    """The hooks ``IRB120TableEnv`` calls: at scene build, at episode reset, on sensor data, around the sim
    steps of a control period. All of them do nothing while ``randomization`` is off."""

    randomization: Randomization = Randomization()
    randomization_draws: dict

    def _init_randomization(self, spec) -> None:
        self.randomization = Randomization.from_any(spec)
        self.randomization_draws = {}
        self._dr_generator: torch.Generator | None = None
        self._dr_noise = False  # depth_noise or depth_dropout on
        self._dr_depth_model: DepthModel | None = None
        self._dr_depth_models: list[DepthModel | None] = []  # a choice of models (``d435|d405|off``), by index
        self._dr_depth_choice: torch.Tensor | None = None  # (num_envs,) each env's index into _dr_depth_models
        self._dr_focal: np.ndarray | None = None  # the sim camera's focal length per env, px
        self._dr_delay: torch.Tensor | None = None
        self._dr_max_delay = 0  # sim steps: the most any env holds its old targets (a Python int, no sync)
        self._dr_substep = 0
        self._dr_nominal: set[int] = set()  # the envs whose current episode was drawn nominal (``nominal``)
        # nominal light colours per env and material colours per (actor, env, shape), read on first use
        self._dr_light_base: dict = {}
        self._dr_color_base: dict = {}
        self._dr_shapes: list[dict[int, list]] = []  # per surface: env -> render shapes

    # ------------------------------------------------------------------ scene build
    @property
    def own_materials(self) -> bool:
        """Build each env's surfaces with materials of their own: an appearance field is active."""
        return bool(set(APPEARANCE_FIELDS) & set(self.randomization.active()))

    def _randomized_build(self, nominal_half_size: float) -> float:
        """The object half size for this build (shared by the envs); checks latency against the period. A new
        scene has new materials: the appearance caches start over."""
        self._dr_shapes, self._dr_color_base = [], {}
        r = self.randomization
        period = 1.0 / self.control_freq
        lat = r.latency if np.isscalar(r.latency) else max(r.latency)
        if lat >= period:
            raise ValueError(f"latency={r.latency!r}: must be shorter than the control period ({period} s)")
        if r.object_size == 1.0:
            return nominal_half_size
        scale = float(r.draw("object_size", _build_rng(self, 0))[0])
        self.randomization_draws["object_size"] = torch.full((self.num_envs,), scale)
        return nominal_half_size * scale

    def _randomize_bodies(self, actor, mass: float, friction: float) -> None:
        r = self.randomization
        if r.object_mass == 1.0 and r.object_friction == 1.0:
            return
        env_of = actor._scene_idxs.cpu().numpy()
        for key, nominal in (("object_mass", mass), ("object_friction", friction)):
            if getattr(r, key) == 1.0:
                continue
            scale = np.array([r.draw(key, _build_rng(self, i))[0] for i in range(self.num_envs)])
            self.randomization_draws[key] = torch.as_tensor(scale * nominal, dtype=torch.float32)
            for body, i in zip(actor._bodies, env_of):
                if key == "object_mass":
                    body.set_mass(float(nominal * scale[i]))
                else:
                    mu = float(nominal * scale[i])
                    for shape in body.get_collision_shapes():
                        shape.set_physical_material(sapien.physx.PhysxMaterial(mu, mu, 0.0))

    # ------------------------------------------------------------------ episode reset
    def _randomize_episode(self, env_idx: torch.Tensor) -> None:
        r = self.randomization
        active = r.active()
        if not active:
            return
        idx = env_idx.cpu().numpy()
        rngs = {int(i): _rng(self, int(i)) for i in idx}
        self._dr_nominal = (self._dr_nominal - {int(i) for i in idx}) | self._draw_nominal(idx)
        per_env = {int(i): self._episode_ranges(int(i)) for i in idx}  # r, or OFF for an env drawn nominal
        cam = self._sensors["hand_camera"].camera if "hand_camera" in self._sensors else None
        if cam is not None and {"camera_pos", "camera_rot", "camera_fov"} & set(active):
            base = self.agent.hand_camera_cfg
            for i in idx:
                ri = per_env[int(i)]
                pos = ri.draw("camera_pos", rngs[i])[0]
                rot = ri.draw("camera_rot", rngs[i])[0]
                nominal = sapien.Pose(p=[float(x) for x in base["offset"]])  # the mount's own axes: no rotation
                cam._render_cameras[i].set_local_pose(nominal * camera_mount_offset(pos, rot))
                fov = base["fov"] if ri.camera_fov is None else math.radians(ri.draw("camera_fov", rngs[i])[0])
                cam._render_cameras[i].set_fovy(fov, compute_x=True)
                self._record_draw("camera_pos", i, pos)
                self._record_draw("camera_rot", i, rot)
                self._record_draw("camera_fov", i, math.degrees(fov))
            cam._cached_local_pose = None
        if "light" in active:
            self._scale_lights({int(i): per_env[int(i)].draw("light", rngs[i])[0] for i in idx})
        if set(APPEARANCE_FIELDS) & set(active):
            self._randomize_appearance(idx, rngs, per_env)
        if "latency" in active:
            if self._dr_delay is None:
                self._dr_delay = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
            steps = [round(per_env[int(i)].draw("latency", rngs[i])[0] * self.sim_freq) for i in idx]
            self._dr_delay[env_idx] = torch.as_tensor(steps, dtype=torch.long, device=self.device)
            self.randomization_draws["latency"] = self._dr_delay.float() / self.sim_freq
            self._dr_max_delay = max(self._dr_max_delay, max(steps))
        if {"depth_noise", "depth_dropout", "depth_model"} & set(active):
            if self._dr_generator is None:
                self._dr_depth = torch.zeros(self.num_envs, 2, device=self.device)  # (std mm, dropout p) per env
                self._dr_generator = torch.Generator(device=self.device)
            for i in idx:
                self._dr_depth[i, 0] = float(per_env[int(i)].draw("depth_noise", rngs[i])[0])
                self._dr_depth[i, 1] = float(per_env[int(i)].draw("depth_dropout", rngs[i])[0])
            self._dr_generator.manual_seed(int(rngs[int(idx[0])].integers(2**62)))
            if {"depth_noise", "depth_dropout"} & set(active):
                self._dr_noise = True
                self.randomization_draws["depth_noise"] = self._dr_depth[:, 0].clone()
                self.randomization_draws["depth_dropout"] = self._dr_depth[:, 1].clone()
            if "depth_model" in active:
                self._set_depth_model(idx, rngs)

    def _draw_nominal(self, idx: np.ndarray) -> set[int]:
        """The reset envs whose episode is nominal (``nominal``), each drawn from its episode seed's own stream
        (not the ranges' stream, which the other envs then draw from as they would without it)."""
        p = float(self.randomization.nominal)
        if p == 0.0:
            return set()
        seeds = getattr(self, "_episode_seed", None)
        out = set()
        for i in (int(i) for i in idx):
            rng = np.random.default_rng([int(seeds[i]), 0xD1]) if seeds is not None else np.random.default_rng()
            if rng.random() < p:
                out.add(i)
            self._record_draw("nominal", i, float(i in out))
        return out

    def _episode_ranges(self, i: int) -> Randomization:
        """What env ``i`` draws its episode from: the ranges, or nothing (OFF) when it was drawn nominal."""
        return _NOMINAL if i in self._dr_nominal else self.randomization

    def _set_depth_model(self, idx: np.ndarray, rngs: dict) -> None:
        """The model and the sim camera's focal length per env (the shadow's width in sim pixels depends on
        it, and ``camera_fov`` may have changed it)."""
        base = self.agent.hand_camera_cfg
        if self._dr_focal is None:
            self._dr_focal = np.full(self.num_envs, base["width"] / 2 / math.tan(base["fov"] / 2))
        fovs = self.randomization_draws.get("camera_fov")
        for i in idx:
            fov = math.radians(float(fovs[i])) if fovs is not None else base["fov"]
            self._dr_focal[i] = base["width"] / 2 / math.tan(fov / 2)
        choices = self.randomization.depth_model
        if isinstance(choices, tuple) or self.randomization.nominal:
            # one model per env: drawn after every other field, so a single preset's streams are unchanged; an env
            # drawn nominal reads the sim's depth ("off", added to the choices when they lack it)
            models = choices if isinstance(choices, tuple) else (choices,)
            models = models if "off" in models or not self.randomization.nominal else (*models, "off")
            if self._dr_depth_choice is None:
                self._dr_depth_choice = torch.zeros(self.num_envs, dtype=torch.long)
            for i in (int(i) for i in idx):
                if i in self._dr_nominal:
                    k = models.index("off")
                else:
                    k = int(rngs[i].integers(len(choices))) if isinstance(choices, tuple) else 0
                self._dr_depth_choice[i] = k
            self._dr_depth_models = [None if n == "off" else preset(n) for n in models]
            self.randomization_draws["depth_model"] = self._dr_depth_choice.float()
        else:
            self._dr_depth_model = preset(choices)
        self._dr_focal_t = torch.as_tensor(self._dr_focal, dtype=torch.float32, device=self.device)

    def _record_draw(self, key: str, i: int, value) -> None:
        v = torch.as_tensor(np.asarray(value, dtype=np.float32))
        if key not in self.randomization_draws:
            self.randomization_draws[key] = torch.zeros((self.num_envs, *v.shape))
        self.randomization_draws[key][i] = v

    def _scale_lights(self, scales: dict[int, float]) -> None:
        for i, scale in scales.items():
            s = self.scene.sub_scenes[i if len(self.scene.sub_scenes) > 1 else 0]
            lights = [c for e in s.entities for c in e.components if isinstance(c, sapien.render.RenderLightComponent)]
            base = self._dr_light_base.setdefault(
                i, ([np.array(c.color) for c in lights], np.array(s.render_system.ambient_light))
            )
            for c, col in zip(lights, base[0]):
                c.color = list(col * scale)
            s.render_system.ambient_light = list(base[1] * scale)
            self._record_draw("light", i, scale)

    def _randomize_appearance(self, idx: np.ndarray, rngs: dict, per_env: dict) -> None:
        """Colour jitter, procedural textures and surface materials of each reset env's own materials; an env
        drawn nominal gets its surfaces' own colours and terms back, untextured."""
        r = self.randomization
        surfaces = [*self._dr_objects, *self.scene_actors]
        if not self._dr_shapes:
            self._dr_shapes = [appearance.render_shapes_per_env(a) for a in surfaces]
        for i in (int(i) for i in idx):
            rng, ri = rngs[i], per_env[i]
            for n, (actor, shapes) in enumerate(zip(surfaces, self._dr_shapes)):
                own = n < len(self._dr_objects) and ri.object_color is not None  # an object with a range of its own
                jitter = rng.uniform(-1, 1, 3) * ri.draw("object_color" if own else "color", rng)[0]
                textured = bool(rng.random() < ri.draw("texture", rng)[0])
                drawn = None  # the first shape's texture and colour, for randomization_draws
                for j, shape in enumerate(shapes.get(i, [])):
                    mat = shape.material
                    # the material as built: colour, roughness, specular (a nominal episode restores them)
                    base = self._dr_color_base.setdefault(
                        (actor.name, i, j), (np.array(mat.base_color), mat.roughness, mat.specular)
                    )
                    rgb = np.clip(base[0][:3] + jitter, 0, 1)
                    mat.base_color = [*rgb, base[0][3]]
                    tex = appearance.draw_texture(rng, rgb) if r.texture != 0.0 and textured else None
                    if r.texture != 0.0:
                        appearance.set_texture(mat, None if tex is None else tex.rgba)
                    drawn = drawn or (rgb, tex)
                    for k, key in enumerate(("roughness", "specular")):
                        if getattr(r, key) is not None:
                            drawn_value = ri.draw(key, rng)[0] if getattr(ri, key) is not None else base[1 + k]
                            setattr(mat, key, float(drawn_value))
                self._record_draw("color_" + actor.name, i, jitter)
                self._record_draw("texture_" + actor.name, i, float(textured))
                if drawn is not None:  # what the camera sees of it: its colour, its pattern (-1: none), contrast
                    self._record_draw("rgb_" + actor.name, i, drawn[0])
                    self._record_draw("pattern_" + actor.name, i, -1.0 if drawn[1] is None else drawn[1].pattern)
                    self._record_draw("contrast_" + actor.name, i, 0.0 if drawn[1] is None else drawn[1].contrast)

    # ------------------------------------------------------------------ each step
    def _randomize_sensor_data(self, data: dict) -> dict:
        """The depth model, then depth noise and dropout, per pixel, from a generator seeded at reset
        (deterministic per seed; one stream for the batch). No host sync: the per-env figures live on the
        device."""
        if self._dr_generator is None or "hand_camera" not in data or "depth" not in data["hand_camera"]:
            return data
        cam = data["hand_camera"]
        depth, g = cam["depth"], self._dr_generator
        if self._dr_depth_model is not None:
            depth = self._dr_depth_model.apply(depth, cam.get("rgb"), self._dr_focal_t, g, float(self._dr_focal.max()))
        elif self._dr_depth_choice is not None:  # each model on the envs that drew it, in the models' order
            rgb, out = cam.get("rgb"), depth.clone()
            for k, model in enumerate(self._dr_depth_models):
                envs = (self._dr_depth_choice == k).nonzero().flatten()
                if model is None or len(envs) == 0:
                    continue
                d = envs.to(depth.device)
                f = self._dr_focal_t[envs.to(self._dr_focal_t.device)]
                out[d] = model.apply(depth[d], None if rgb is None else rgb[d], f, g, float(self._dr_focal.max()))
            depth = out
        if self._dr_noise:
            # the frame can live on the render device (CUDA) while the sim and the generator are on the CPU
            dev = depth.device
            std, p = (self._dr_depth[:, i, None, None, None].to(dev) for i in (0, 1))
            noisy = depth.float() + drawn(torch.randn, depth.shape, g, dev) * std
            noisy = torch.where(drawn(torch.rand, depth.shape, g, dev) < p, 0.0, noisy)
            keep = depth > 0  # "no reading" stays no reading
            depth = torch.where(keep, noisy.round().clamp(0, 32767), 0).to(depth.dtype)
        cam["depth"] = depth
        return data

    def _step_action(self, action):
        if self._dr_delay is not None:
            # the targets in force: after a reset the drives have none yet, the robot holds where it stands
            robot = self.agent.robot
            self._dr_old_targets = torch.where(self._fresh[:, None], robot.get_qpos(), robot.get_drive_targets())
            self._dr_substep = 0
        return super()._step_action(action)

    def _before_simulation_step(self):
        if self._dr_delay is not None and self._dr_substep <= self._dr_max_delay:
            if self._dr_substep == 0:
                self._dr_new_targets = self.agent.robot.get_drive_targets().clone()
            held = (self._dr_delay > self._dr_substep)[:, None]
            robot = self.agent.robot
            robot.set_joint_drive_targets(
                torch.where(held, self._dr_old_targets, self._dr_new_targets), robot.active_joints
            )
            if self.gpu_sim_enabled:
                self.scene.px.gpu_apply_articulation_target_position()
        self._dr_substep += 1
        super()._before_simulation_step()
