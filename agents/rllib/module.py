"""RLlib's default PPO / APPO / SAC RLModules with our RGB-D + proprioception encoder for dict observations.

RLlib has no default encoder for a ``Dict`` observation (and flattening an 84x84x4 image into an MLP input
would throw the image structure away). The encoder here *is* :class:`maniskill_irb120.policies.nets.NatureCNN`, the one
``agents.ppo`` trains, plugged into RLlib through its Catalog: the default modules keep their heads, value
function, Q networks and target networks; only the observation encoder is ours. State observations (a flat
``Box``) keep RLlib's default MLP encoder."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import gymnasium as gym
from ray.rllib.algorithms.ppo.ppo_catalog import PPOCatalog
from ray.rllib.algorithms.sac.sac_catalog import SACCatalog
from ray.rllib.core.columns import Columns
from ray.rllib.core.models.base import ENCODER_OUT, Encoder
from ray.rllib.core.models.configs import ModelConfig
from ray.rllib.core.models.torch.base import TorchModel
from ray.rllib.core.rl_module.rl_module import RLModuleSpec

from agents.common import shapes_of
from maniskill_irb120.policies.nets import NatureCNN


@dataclass
class RGBDEncoderConfig(ModelConfig):
    """Config of :class:`TorchRGBDEncoder` (a catalog hands one to every encoder slot a module has)."""

    image_shape: Optional[tuple[int, int, int]] = None
    state_dim: int = 0
    feature_dim: int = 256

    @property
    def output_dims(self) -> tuple[int]:
        return ((self.feature_dim if self.image_shape else 0) + 256,)

    def build(self, framework: str = "torch") -> Encoder:
        if framework != "torch":
            raise ValueError(f"the RGB-D encoder is torch only, got framework={framework!r}")
        return TorchRGBDEncoder(self)


class TorchRGBDEncoder(TorchModel, Encoder):
    """``{OBS: {rgb, depth, state}}`` -> ``{ENCODER_OUT: features}`` through the shared NatureCNN."""

    def __init__(self, config: RGBDEncoderConfig):
        TorchModel.__init__(self, config)
        Encoder.__init__(self, config)
        self.net = NatureCNN(config.image_shape, config.state_dim, config.feature_dim)

    def _forward(self, inputs: dict, **kwargs) -> dict:
        return {ENCODER_OUT: self.net(inputs[Columns.OBS])}


def _encoder_config(catalog_cls, observation_space, model_config_dict, action_space=None) -> ModelConfig:
    if isinstance(observation_space, gym.spaces.Dict):
        missing = {"rgb", "depth", "state"} - set(observation_space.spaces)
        if missing:
            raise ValueError(
                f"the RGB-D encoder needs obs keys rgb, depth and state (FlattenRGBDObservationWrapper); "
                f"missing {sorted(missing)}"
            )
        image_shape, state_dim = shapes_of(observation_space)
        return RGBDEncoderConfig(image_shape=tuple(image_shape), state_dim=state_dim)
    return super(catalog_cls, catalog_cls)._get_encoder_config(
        observation_space=observation_space, model_config_dict=model_config_dict, action_space=action_space
    )


class RGBDPPOCatalog(PPOCatalog):
    """PPO's and APPO's catalog with the RGB-D encoder for dict observations (shared by actor and critic
    unless ``vf_share_layers`` is off, as RLlib decides)."""

    @classmethod
    def _get_encoder_config(cls, observation_space, model_config_dict, action_space=None):
        return _encoder_config(RGBDPPOCatalog, observation_space, model_config_dict, action_space)


class RGBDSACCatalog(SACCatalog):
    """SAC's catalog with the RGB-D encoder: the actor's encoder, and the observation stream of each
    Q network's (and target Q network's) obs + action encoder."""

    @classmethod
    def _get_encoder_config(cls, observation_space, model_config_dict, action_space=None):
        return _encoder_config(RGBDSACCatalog, observation_space, model_config_dict, action_space)


def module_spec(algo: str, model_config: Optional[dict] = None) -> RLModuleSpec:
    """The RLModuleSpec to give ``config.rl_module``: RLlib's default module class for ``algo``, our catalog."""
    catalogs = {"PPO": RGBDPPOCatalog, "APPO": RGBDPPOCatalog, "SAC": RGBDSACCatalog}
    if algo not in catalogs:
        raise ValueError(f"unknown algo {algo!r}; use one of {sorted(catalogs)}")
    return RLModuleSpec(catalog_class=catalogs[algo], model_config=model_config)
