"""Registers lerobot-crowdnav's ``crowdnav`` EnvConfig when lerobot loads its plugins."""

from lerobot_crowdnav.sim.lerobot_env import CrowdNavEnvConfig

__all__ = ["CrowdNavEnvConfig"]
