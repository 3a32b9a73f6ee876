"""lerobot-crowdnav: diffusion-policy robot crowd navigation (PDPO) in the LeRobot ecosystem.

Importing the package registers the gymnasium environments ``lerobot_crowdnav/CrowdNav-v0`` and
``lerobot_crowdnav/BoundedCrowdNav-v0`` (``gym.make("lerobot_crowdnav:lerobot_crowdnav/CrowdNav-v0")``
imports it for you). The compiled simulator is loaded on first use, not at import.
"""

import gymnasium as gym

from .sim.config import PRESETS, SEED_SPLITS, TASKS, CrowdSimConfig, split_seeds

__all__ = ["CrowdSimConfig", "PRESETS", "SEED_SPLITS", "TASKS", "split_seeds"]
__version__ = "0.1.0"


def _register() -> None:
    for task in TASKS:
        env_id = f"lerobot_crowdnav/{task}"
        if env_id not in gym.registry:
            gym.register(
                id=env_id,
                entry_point="lerobot_crowdnav.sim.envs:CrowdNavEnv",
                vector_entry_point="lerobot_crowdnav.sim.envs:CrowdNavVectorEnv",
                kwargs={"task": task},
                disable_env_checker=False,
            )


_register()
