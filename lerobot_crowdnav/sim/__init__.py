"""The simulator layer: ``config`` (CrowdSimConfig, presets, seed splits) <- ``orca`` (RVO2 in
numba) <- ``engine`` (the batched compiled CrowdSim) <- ``envs`` (gymnasium single and vector envs)
<- ``render``, ``lerobot_env`` (lerobot's ``crowdnav`` EnvConfig), ``benchmark`` (the bench CLI).

Imports nothing at package import: ``lerobot_crowdnav.sim.config`` stays light (no numba), the
compiled engine loads on first use. See docs/architecture.md for the layers.
"""
