"""PDPO processors: normalization in (state mean/std, actions to [-1, 1]), denormalization out.

lerobot's own pipeline (rename, batch, device, normalize / unnormalize, cpu) with one change to
the statistics: the human-row columns of ``observation.state`` hold the sentinel 15 wherever a
human is invisible, which would dominate their mean and std. Since a sentinel row is exactly 15
in all of its columns and the dataset's mask columns give each row's visible fraction, the
visible-only moments follow from the stored ones:

    mean_vis = (mean - p S) / (1 - p),   E_vis[x^2] = (std^2 + mean^2 - p S^2) / (1 - p)

(p = invisible fraction of the row, S = 15). They are pooled over the N rows (weighted by their
visible counts: every row holds the same kind of data) and used for every row; the mask columns
are left as 0/1. The corrected statistics are what the checkpoint's normalizer saves.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors
from lerobot.utils.constants import OBS_STATE

from lerobot_crowdnav.layout import humans_slice

from .configuration_pdpo import PDPOConfig


def _np(x) -> np.ndarray:
    return x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, np.float64)


def crowd_state_stats(state_stats: dict, config: PDPOConfig) -> dict[str, np.ndarray]:
    """``observation.state`` statistics with the human rows' mean/std computed over visible rows
    only and the mask columns mapped to mean 0, std 1 (identity)."""
    n, row = config.num_humans, 2 * (config.prediction_steps + 1)
    humans = humans_slice(n, config.prediction_steps)
    h0, h1 = humans.start, humans.stop
    stats = {k: _np(v).copy() for k, v in state_stats.items()}
    mean, std = stats["mean"], stats["std"]
    if mean.shape != (h1 + n,):
        raise ValueError(f"{OBS_STATE} statistics have {mean.shape[0]} values; the config expects {h1 + n}")
    if np.all(mean[h1:] == 0) and np.all(std[h1:] == 1):
        return stats  # already corrected (e.g. statistics read back from a checkpoint)
    visible = np.clip(mean[h1:], 0.0, 1.0)[:, None]  # (N, 1) visible fraction of each row
    if visible.sum() <= 0:
        raise ValueError("no human is ever visible in the dataset: human statistics are undefined")
    s = config.sentinel_value
    row_mean, row_std = mean[h0:h1].reshape(n, row), std[h0:h1].reshape(n, row)
    hidden = 1.0 - visible
    pooled_mean = (row_mean - hidden * s).sum(0) / visible.sum()
    pooled_sq = (row_std**2 + row_mean**2 - hidden * s * s).sum(0) / visible.sum()
    pooled_std = np.sqrt(np.maximum(pooled_sq - pooled_mean**2, 1e-12))
    mean[h0:h1] = np.tile(pooled_mean, n)
    std[h0:h1] = np.tile(pooled_std, n)
    mean[h1:], std[h1:] = 0.0, 1.0
    return stats


def make_pdpo_pre_post_processors(
    config: PDPOConfig, dataset_stats: dict[str, dict[str, Any]] | None = None
) -> tuple[PolicyProcessorPipeline[dict[str, Any], dict[str, Any]], PolicyProcessorPipeline[PolicyAction, PolicyAction]]:
    if dataset_stats is not None and OBS_STATE in dataset_stats:
        dataset_stats = {**dataset_stats, OBS_STATE: crowd_state_stats(dataset_stats[OBS_STATE], config)}
    return make_default_pre_post_processors(config, dataset_stats)
