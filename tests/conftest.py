"""Test-suite settings and shared helpers.

Property tests draw the same examples on every run (reproducible CI). ``small_pdpo_config`` and
``make_tiny_checkpoint`` build a small PDPO policy saved the way lerobot-train saves one.
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

from hypothesis import settings

# 🤗 datasets keeps an Arrow copy of every dataset it loads (lerobot-train, DAgger rounds, the
# tests' tiny datasets) in its cache, and nothing deletes them: the suite's go to a folder removed
# at exit instead of the user's ~/.cache. Set before anything imports datasets (it reads it then).
HF_DATASETS_CACHE = tempfile.mkdtemp(prefix="lerobot-crowdnav-tests-hf-")
os.environ["HF_DATASETS_CACHE"] = HF_DATASETS_CACHE
atexit.register(shutil.rmtree, HF_DATASETS_CACHE, ignore_errors=True)

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
