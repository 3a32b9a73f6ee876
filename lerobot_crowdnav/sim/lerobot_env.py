"""The crowd env as a lerobot ``EnvConfig``: ``--env.type=crowdnav --env.task=BoundedCrowdNav-v0``.

Every simulator field is a flag (``--env.preset=crowdnavpp --env.randomize_attributes=false``).
lerobot discovers this module through the ``lerobot_env_crowdnav`` plugin distribution (see
``plugins/``), installed by the README's set-up. ``create_envs`` returns the native batched env,
with dict observations ``{"agent_pos": (B, 269)}`` that lerobot maps to ``observation.state``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_STATE

from .config import CrowdSimConfig
from .envs import CrowdNavVectorEnv


@EnvConfig.register_subclass("crowdnav")
@dataclass
class CrowdNavEnvConfig(CrowdSimConfig, EnvConfig):
    """Crowd navigation for lerobot-train / lerobot-eval (fields: see ``CrowdSimConfig``)."""

    fps: int = 4  # control at dt = 0.25 s
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(default_factory=lambda: {ACTION: ACTION, "agent_pos": OBS_STATE})

    def __post_init__(self):
        sim = self.resolve()  # validates the fields early, with a clear message
        self.features = {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(2,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(sim.obs_dim,)),
        }

    @property
    def gym_kwargs(self) -> dict:
        return {"config": self.resolve()}

    def create_envs(self, n_envs: int, use_async_envs: bool = False):
        """One native batched env (``use_async_envs`` is moot: the batch is one compiled call),
        whose ended slots report nothing more until the next rollout (``freeze_ended``)."""
        env = CrowdNavVectorEnv(n_envs, render_mode="rgb_array", obs_mode="dict", freeze_ended=True,
                                config=self.resolve())
        return {self.type: {0: env}}
