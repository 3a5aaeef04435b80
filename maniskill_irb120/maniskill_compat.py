"""Where this package relies on ManiSkill internals that are not public API (mirrors ManiSkill 3.0.1).

Everything here was read against ``mani_skill`` 3.0.1 (``envs/sapien_env.py``, ``envs/scene.py``,
``agents/controllers/*``). ``tests/test_maniskill_compat.py`` pins each assumption, so an upgrade that
changes one fails there first, not somewhere downstream in training.

What is here: partial-reset masks for controllers and controller-state restore (below), direct PhysX
drive-target writes and pose reads on the CPU (:func:`set_drive_targets`, :func:`raw_pose`), where SAPIEN keeps
PhysX's GPU library (:func:`physx_gpu_library`), and the
render-ahead read-back of a camera frame whose capture the task already started (:func:`read_sensor_obs`).

Partial resets: ``BaseEnv.reset`` sets ``scene._reset_mask`` to the envs being reset while it runs
``_initialize_episode``, then sets it back to all-true *before* it resets the controllers. Every
controller that writes ``target[scene._reset_mask] = ...`` in ``reset()`` (ManiSkill's joint and EE
controllers, ours) therefore resets every env's targets whenever any env resets: with
``pd_ee_target_delta_tool`` (accumulated targets) or ``interpolate`` that corrupts running episodes on
the GPU. The task records the true mask for the duration of its reset (:func:`episode_reset`) and
:class:`PartialResetControllerMixin` puts it in place while a controller resets.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

MANISKILL_VERSION = "3.0.1"
_MASK_ATTR = "_irb120_episode_reset_mask"


def reset_mask_from_options(num_envs: int, options: dict | None, device) -> torch.Tensor:
    """(N,) bool: the envs a ``reset(options=...)`` call resets (all of them without ``env_idx``)."""
    if options is None or "env_idx" not in options:
        return torch.ones(num_envs, dtype=torch.bool, device=device)
    mask = torch.zeros(num_envs, dtype=torch.bool, device=device)
    mask[torch.as_tensor(options["env_idx"], device=device).long()] = True
    return mask


@contextmanager
def episode_reset(scene, mask: torch.Tensor) -> Iterator[None]:
    """Record ``mask`` as the envs of the reset in progress on ``scene`` (see the module docstring).

    A reset that reconfigures builds a new scene: that one carries no mask, and all of its envs are
    new, which is what the fallback to ``scene._reset_mask`` (all-true then) says."""
    setattr(scene, _MASK_ATTR, mask)
    try:
        yield
    finally:
        setattr(scene, _MASK_ATTR, None)


def episode_reset_mask(scene) -> torch.Tensor:
    """The envs being reset: the task's record during its reset, else ManiSkill's ``_reset_mask``."""
    mask = getattr(scene, _MASK_ATTR, None)
    return scene._reset_mask if mask is None else mask


@contextmanager
def true_reset_mask(scene) -> Iterator[torch.Tensor]:
    """Put the envs being reset in ``scene._reset_mask`` for the block (controller resets), then restore."""
    saved = scene._reset_mask
    scene._reset_mask = episode_reset_mask(scene)
    try:
        yield scene._reset_mask
    finally:
        scene._reset_mask = saved


class PartialResetControllerMixin:
    """Resets only the envs being reset. Put it first among the bases of a ManiSkill controller class
    that does not override ``reset`` itself; the inherited ``reset()`` then masks with the right envs."""

    def reset(self) -> None:
        with true_reset_mask(self.scene):
            super().reset()


def _unflatten_like(template: dict, flat: torch.Tensor) -> dict:
    """Inverse of ManiSkill's ``common.flatten_state_dict`` for a dict of (N, k) tensors like ``template``."""
    out, start = {}, 0
    for key, value in template.items():
        if isinstance(value, dict):
            width = sum(_width(v) for v in value.values())
            out[key] = _unflatten_like(value, flat[:, start : start + width])
        else:
            width = _width(value)
            out[key] = flat[:, start : start + width]
        start += width
    return out


def _width(value) -> int:
    return sum(_width(v) for v in value.values()) if isinstance(value, dict) else int(value.shape[-1])


def _merge_rows(current: dict, new: dict, env_idx) -> dict:
    """``current`` with the rows ``env_idx`` replaced by ``new``'s rows (all rows when ``env_idx`` is None)."""
    out = {}
    for key, cur in current.items():
        if isinstance(cur, dict):
            out[key] = _merge_rows(cur, new[key], env_idx)
        elif env_idx is None:
            out[key] = torch.as_tensor(new[key], device=cur.device, dtype=cur.dtype).reshape(cur.shape).clone()
        else:
            merged = cur.clone()
            merged[torch.as_tensor(env_idx, device=cur.device).long()] = torch.as_tensor(
                new[key], device=cur.device, dtype=cur.dtype
            ).reshape(-1, *cur.shape[1:])
            out[key] = merged
    return out


def state_extras(env, state) -> dict:
    """The parts of an env state that ManiSkill 3.0.1's ``set_state_dict`` / ``set_state`` do not restore: the
    ``"controller"`` part ManiSkill records, and the ``"memory"`` part this project's envs add
    (``IRB120TableEnv.get_state_dict``), each present only where ``state`` has it.

    ``state``: the state dict, or the flat state vector, whose tail after the actors and articulations holds these
    parts in ``get_state_dict`` order. A flat state of an older layout (no memory), or with no tail, gives the parts
    it has; one whose tail fits no prefix of this env's layout (recorded in another control mode) gives none."""
    if isinstance(state, dict):
        return {k: state[k] for k in ("controller", "memory") if k in state}
    flat = torch.as_tensor(state)
    flat = flat[None] if flat.dim() == 1 else flat
    raw = env._init_raw_state
    base = sum(int(a.shape[-1]) for part in ("actors", "articulations") for a in raw[part].values())
    width, layout, used = flat.shape[1] - base, {}, 0
    for key in ("controller", "memory"):
        if key in raw and used + _width(raw[key]) <= width:
            layout[key] = raw[key]
            used += _width(raw[key])
    if used != width:
        return {}
    return _unflatten_like(layout, flat[:, base:])


def restore_controller_state(env, state, env_idx=None) -> None:
    """Restore the controller state that ``env.get_state_dict()`` / ``get_state()`` record and ManiSkill
    3.0.1's ``set_state_dict`` / ``set_state`` drop (e.g. ``pd_ee_target_delta_tool``'s accumulated
    targets: without them a restored episode's next action starts from the wrong target).

    ``state``: the state dict or the flat state vector (:func:`state_extras`). Rows are those of ``env_idx`` (all
    envs when None), as ManiSkill's."""
    current = env.agent.get_controller_state()
    ctrl = state_extras(env, state).get("controller")
    if not current or ctrl is None:
        return
    env.agent.set_controller_state(_merge_rows(current, ctrl, env_idx))


def set_drive_targets(ctrl, targets: torch.Tensor) -> None:
    """Joint drive targets of a ManiSkill joint controller. ManiSkill's CPU path converts and validates
    each joint's target through three Python layers (~12 us per joint, 8 joints per step); this writes
    the floats to the PhysX joints directly. GPU: ManiSkill's own (batched) path."""
    if ctrl.scene.gpu_sim_enabled:  # what PDJointPosController.set_drive_targets does
        ctrl.articulation.set_joint_drive_targets(targets, ctrl.joints, ctrl.active_joint_indices)
        return
    row = targets[0].detach().numpy()
    for i, joint in enumerate(ctrl.joints):
        joint._objs[0].drive_target = row[i : i + 1]


def raw_pose(obj) -> torch.Tensor:
    """(N, 7) raw pose (position, wxyz quaternion) of a ManiSkill ``Actor`` or ``Link``: ``obj.pose.raw_pose``. On
    the CPU ManiSkill builds it through ``Pose.create`` and ``to_tensor`` from a list of SAPIEN poses, several times
    slower than reading the same float32 numbers straight from SAPIEN, as this does (entity poses, and a link's
    ``entity_pose``, as ManiSkill's CPU branch reads them; the tasks read two a step; docs/notes/sim-speed.md).
    GPU: ManiSkill's batched buffers."""
    if obj.scene.gpu_sim_enabled:
        return obj.pose.raw_pose
    from sapien.physx import PhysxArticulationLinkComponent

    poses = [o.entity_pose if isinstance(o, PhysxArticulationLinkComponent) else o.pose for o in obj._objs]
    return torch.from_numpy(
        np.concatenate([np.concatenate([p.p, p.q])[None] for p in poses]).astype(np.float32, copy=False)
    )


def read_sensor_obs(env, apply_texture_transforms: bool = True) -> dict:
    """``BaseEnv._get_obs_sensor_data`` without its ``update_render`` + ``capture_sensor_data``: for a
    frame whose capture was already started (render-ahead); a second update would only mark it stale."""
    from mani_skill.sensors.camera import Camera

    v = env.obs_mode_struct.visual
    return {
        name: sensor.get_obs(
            rgb=v.rgb,
            depth=v.depth,
            position=v.position,
            segmentation=v.segmentation,
            normal=v.normal,
            albedo=v.albedo,
            apply_texture_transforms=apply_texture_transforms,
        )
        if isinstance(sensor, Camera)
        else sensor.get_obs()
        for name, sensor in env.scene.sensors.items()
    }


def physx_gpu_library() -> tuple[Path, str]:
    """(where SAPIEN looks for PhysX's GPU library, the archive it fetches there on first GPU use), as
    ``sapien.physx.enable_gpu`` builds them (Linux x86-64). ``physx_cuda`` cannot start without that file,
    and a machine that cannot reach GitHub never gets it: the GPU acceptance suite names both, so the fix
    (unzip the archive at the path's folder) is one step."""
    import sapien

    version = sapien.physx.version()
    url = f"https://github.com/sapien-sim/physx-precompiled/releases/download/{version}/linux-so.zip"
    return Path.home() / ".sapien" / "physx" / version / "libPhysXGpu_64.so", url
