"""Test-suite settings and shared helpers.

Property tests draw the same examples on every run (reproducible CI). ``small_pdpo_config`` and
``make_tiny_checkpoint`` build a small PDPO policy saved the way lerobot-train saves one.
"""

from __future__ import annotations

from pathlib import Path

from hypothesis import settings

settings.register_profile("reproducible", derandomize=True, deadline=None)
settings.load_profile("reproducible")

# A PDPO small enough for fast tests (same structure as the paper's).
SMALL = dict(human_mlp_dims=(32, 32), attention_heads=2, edge_mlp_dims=(64, 64), pool_mlp_dims=(32,),
             latent_mlp_dims=(64, 32), denoiser_dims=(64, 64), value_mlp_dims=(32, 32))


def small_pdpo_config(**overrides):
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot_policy_pdpo import PDPOConfig

    return PDPOConfig(input_features={"observation.state": PolicyFeature(FeatureType.STATE, (269,))},
                      output_features={"action": PolicyFeature(FeatureType.ACTION, (2,))}, device="cpu",
                      **{**SMALL, **overrides})


def make_tiny_checkpoint(root: Path, **overrides) -> Path:
    """An untrained small PDPO checkpoint with the statistics of an 8-episode ORCA dataset:
    ``root/pretrained_model`` with config, weights and processors, as lerobot-train saves it."""
    from lerobot_crowdnav.data.collect import main as collect_main
    from fault_injection import untrained_checkpoint

    collect_main(["--episodes=8", "--batch_size=8", f"--root={root / 'ds'}", f"--repo_id=local/{root.name}"])
    return untrained_checkpoint(root, root / "ds", small_pdpo_config(**overrides))
