"""The row type both sources of the main job produce (``sources.ShippedModels``,
``sources.TrainedFromScratch``) and the evaluation consumes: a labelled table row of policies to
evaluate on the test seeds, one per training seed."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..evaluation.report import Stage

FINETUNED_LABEL = {5: "PDPO (H = 5, fine-tuned)", 1: "PDPO w/o action chunk (H = 1, fine-tuned)"}
CROWDNAVPP_LABEL = "CrowdNav++ (Const. Vel.)"


def finetuned_label(h: int) -> str:
    return FINETUNED_LABEL.get(h, f"PDPO (H = {h}, fine-tuned)")


@dataclass(frozen=True)
class Evaluation:
    """One policy to evaluate on the test seeds: a built-in (``policy`` None), a checkpoint this
    run trained (``pretrain``: its lerobot-train stage; ``finetune``: the PPO stage whose ``best``
    it is, diffusion PPO's last or CrowdNav++'s), or a ``shipped`` model directory."""

    name: str  # the directory under eval/<task>/
    policy: Path | None = None
    horizon: int | None = None
    seed: int | None = None
    shipped: bool = False
    pretrain: Stage | None = None
    finetune: Stage | None = None
    policy_type: str | None = None  # a built-in's --policy.type (default: name)
    env_flags: tuple[str, ...] = ()  # lerobot-crowdnav-eval's --env flags beyond the run's task and preset


@dataclass(frozen=True)
class MethodRow:
    """A table row: its label and its evaluations (averaged in the row)."""

    label: str
    evaluations: list[Evaluation]
