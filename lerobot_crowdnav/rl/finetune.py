"""Online diffusion-PPO fine-tuning of a pretrained PDPO policy (DPPO): ``lerobot-crowdnav-finetune``.

    lerobot-crowdnav-finetune --policy.path=outputs/train/bounded_pdpo/checkpoints/last/pretrained_model \\
        --env.task=BoundedCrowdNav-v0 --env_steps=12000000 --output_dir=outputs/finetune/bounded_pdpo
    lerobot-crowdnav-finetune --config_path=configs/finetune/bounded_pdpo.yaml [--resume=true]
    accelerate launch --num_processes=2 -m lerobot_crowdnav.rl.finetune ...   # DDP, one env batch per process

The run is the shared PPO run (rl/trainer.py: collect, update, validation, checkpoints, resume,
logs, DDP) with the DPPO agent (rl/dppo.py). See docs/finetune.md for every choice and the
output directory.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..checkpoint_files import FINETUNE_CONFIG
from ..cli import run_cli
from ..sim.config import CrowdSimConfig
from .config import DiffusionPPOConfig
from .dppo import check_compatible, load_agent
from .trainer import PPORunConfig, ValidationConfig, WandBConfig, crossed, run_ppo

__all__ = ["FinetuneConfig", "PolicySource", "ValidationConfig", "WandBConfig", "crossed", "finetune", "main"]


@dataclass
class PolicySource:
    # Pretrained PDPO checkpoint to fine-tune: a pretrained_model directory written by
    # lerobot-train (or by this command), or a hub-format model directory.
    path: Path | None = None


@dataclass
class FinetuneConfig(PPORunConfig):
    # --policy.path=<pretrained PDPO checkpoint>
    policy: PolicySource = field(default_factory=PolicySource)
    # Envs stepped together by each process.
    num_envs: int = 64
    # Budget in environment steps, all processes together (paper: about 12 M).
    env_steps: int = 12_000_000
    ppo: DiffusionPPOConfig = field(default_factory=DiffusionPPOConfig)


def finetune(cfg: FinetuneConfig) -> dict:
    """One process (rank) of the run (rl/trainer.py ``run_ppo``) with the DPPO agent."""

    def build_agent(source: Path | None, sim_cfg: CrowdSimConfig):
        if source is None:
            raise ValueError("--policy.path=<pretrained PDPO checkpoint> is required")
        agent = load_agent(source, cfg.ppo, cfg.seed)
        check_compatible(agent.policy, sim_cfg)
        return agent

    return run_ppo(cfg, build_agent, cfg.policy.path, command="finetune", config_name=FINETUNE_CONFIG,
                   label="diffusion PPO", done="fine-tuned")


def main(argv: list[str] | None = None) -> None:
    run_cli(FinetuneConfig, finetune, argv, "rerun the same command with --resume=true to continue from the last checkpoint")


if __name__ == "__main__":
    main()
