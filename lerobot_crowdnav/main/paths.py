"""The main job's run folder and stage names: where every stage writes, and what it is called.

    outputs/<run>/
        main_config.json, stage_times.json, stage_cpu.json (main.stages.CPU_TIMES)
        datasets/<task>/               ORCA demonstrations (LeRobotDataset); with DAgger, each
                                       policy's own copy, <task>_h<H>_s<seed>_dagger/
        train/<task>_h<H>_s<seed>/     lerobot-train runs (checkpoints/last/pretrained_model)
        finetune/<task>_h<H>_s<seed>/  diffusion-PPO runs (checkpoints/best/pretrained_model); with
                                       --ft2_env_steps, <...>_stage2/ continues from it (--ft2_from)
        crowdnavpp/<task>_s<seed>/     CrowdNav++ PPO runs (checkpoints/best/pretrained_model)
        select/<task>_h<H>_s<seed>/    with --select_top, the checkpoint choice on the validation
        select/crowdnavpp_<task>_s<seed>/  seeds: each candidate's metrics.json, selected.json
        eval/<task>/<method>/          metrics.json (+ a GIF of the first test episode)
        eval/<task>/<method>_<crowd>/  the same under another crowd (--crowds: reactive_orca,
                                       social_force, reactive_social_force), no GIF
        hub/                           datasets/<org>/<name>, models/<org>/<name>
        figures/<task>/                storyboard, multimodality, fine-tuning curves
        tables/*.csv, commands.json, report.md
        .hf_datasets_cache/            while a lerobot-train segment runs: 🤗 datasets' Arrow copy of
                                       its dataset, removed after the segment

A learned policy's metrics.json (in eval/ and select/) and figures/<task>/ have policy.sha256
beside them, the digest of the policy they were made from: another policy at the same path (a
longer run, another checkpoint chosen, a run redone) makes them again.

<task> is ``bounded`` or ``original``. A stage is skipped when its output here is complete, and
its wall time is summed under its name in ``stage_times.json``, its CPU time in ``stage_cpu.json``
(the model cards' cost tables read both), so a run in progress resumes on these paths and names: change none of them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..evaluation.generalization import TRAINED, crowd_dir

SHORT = {"BoundedCrowdNav-v0": "bounded", "CrowdNav-v0": "original"}
TITLE = {"BoundedCrowdNav-v0": "Bounded CrowdNav", "CrowdNav-v0": "original CrowdNav"}


@dataclass(frozen=True)
class RunPaths:
    """The folder of one run, ``<output_root>/<run>``, and the hub organization of its pushes."""

    root: Path
    hub_org: str = "local"

    @property
    def config_file(self) -> Path:
        return self.root / "main_config.json"

    @property
    def stage_times(self) -> Path:
        return self.root / "stage_times.json"

    @property
    def hub(self) -> Path:
        return self.root / "hub"

    @property
    def datasets_cache(self) -> Path:
        return self.root / ".hf_datasets_cache"

    def dataset_root(self, task: str) -> Path:
        return self.root / "datasets" / SHORT[task]

    def dagger_dataset_root(self, task: str, h: int, seed: int) -> Path:
        """One policy's copy of the demonstrations that its DAgger rounds aggregate into."""
        return self.root / "datasets" / f"{SHORT[task]}_h{h}_s{seed}_dagger"

    def repo_id(self, task: str, orca_robot: str = "look_ahead") -> str:
        """The demonstrations' name: the paper's look-ahead ORCA robot's plain, another
        demonstrator's suffixed, so that the two never publish under one name."""
        suffix = "" if orca_robot == "look_ahead" else f"_{orca_robot}"
        return f"{self.hub_org}/crowdnav_orca_{SHORT[task]}{suffix}"

    def train_dir(self, task: str, h: int, seed: int) -> Path:
        return self.root / "train" / f"{SHORT[task]}_h{h}_s{seed}"

    def finetune_dir(self, task: str, h: int, seed: int, stage: int = 1) -> Path:
        return self.root / "finetune" / (f"{SHORT[task]}_h{h}_s{seed}" + ("" if stage == 1 else f"_stage{stage}"))

    def select_dir(self, task: str, h: int | None, seed: int) -> Path:
        """The checkpoint choice of a PDPO policy, or with ``h=None`` of a CrowdNav++ run
        (``--select_top``): each candidate's validation metrics and ``selected.json``."""
        return self.root / "select" / (f"{SHORT[task]}_h{h}_s{seed}" if h is not None else f"crowdnavpp_{SHORT[task]}_s{seed}")

    def selected_file(self, task: str, h: int | None, seed: int) -> Path:
        return self.select_dir(task, h, seed) / "selected.json"

    def crowdnavpp_dir(self, task: str, seed: int) -> Path:
        return self.root / "crowdnavpp" / f"{SHORT[task]}_s{seed}"

    def eval_dir(self, task: str, name: str, crowd: str = TRAINED) -> Path:
        """A policy's test-seed evaluation; under a crowd other than the trained one, the same
        name with the crowd as a suffix."""
        return crowd_dir(self.root / "eval" / SHORT[task] / name, crowd)

    def figures_dir(self, task: str) -> Path:
        return self.root / "figures" / SHORT[task]


# Stage names: the keys of stage_times.json and commands.json, the rows of the report's Stages
# table and of each model card's wall times.
def collect_stage(task: str) -> str:
    return f"collect {SHORT[task]}"


def pretrain_stage(task: str, h: int, seed: int) -> str:
    return f"pretrain {SHORT[task]} H={h} seed={seed}"


def finetune_stage(task: str, h: int, seed: int, stage: int) -> str:
    return f"finetune{'' if stage == 1 else stage} {SHORT[task]} H={h} seed={seed}"


def select_stage(task: str, h: int | None, seed: int) -> str:
    return f"select {SHORT[task]} H={h} seed={seed}" if h is not None else f"select crowdnavpp {SHORT[task]} seed={seed}"


def crowdnavpp_stage(task: str, seed: int) -> str:
    return f"train crowdnavpp {SHORT[task]} seed={seed}"


def eval_stage(task: str, name: str, crowd: str = TRAINED) -> str:
    return f"eval {SHORT[task]} {name}" + ("" if crowd == TRAINED else f" crowd={crowd}")


def push_dataset_stage(task: str) -> str:
    return f"push dataset {SHORT[task]}"


def push_policy_stage(task: str, name: str) -> str:
    return f"push policy {SHORT[task]} {name}"


def figures_stage(task: str) -> str:
    return f"figures {SHORT[task]}"
