"""CrowdNav++ processors: identity normalization (lerobot's default pipeline: rename, batch,
device in; cpu out). The reference normalizes neither observations nor actions: the network reads
metres and m/s and outputs world-frame velocities in m/s, which the env clips by norm to v_pref."""

from __future__ import annotations

from typing import Any

from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from .configuration_crowdnavpp import CrowdNavPPConfig


def make_crowdnavpp_pre_post_processors(
    config: CrowdNavPPConfig, dataset_stats: dict[str, dict[str, Any]] | None = None
) -> tuple[PolicyProcessorPipeline[dict[str, Any], dict[str, Any]], PolicyProcessorPipeline[PolicyAction, PolicyAction]]:
    return make_default_pre_post_processors(config, None)
