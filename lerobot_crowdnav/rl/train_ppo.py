"""PPO from scratch of an actor-critic policy (CrowdNav++): ``lerobot-crowdnav-train-ppo``.

    lerobot-crowdnav-train-ppo --policy.type=crowdnavpp --env.task=CrowdNav-v0 --env.preset=crowdnavpp \\
        --output_dir=outputs/train_ppo/crowdnavpp_original
    lerobot-crowdnav-train-ppo --config_path=configs/rl/crowdnavpp_bounded.yaml [--resume=true]
    accelerate launch --num_processes=2 -m lerobot_crowdnav.rl.train_ppo ...   # DDP, one env batch per process

The run is the shared PPO run (rl/trainer.py: collect, update, validation, checkpoints, resume,
logs, DDP) with the policy's agent (rl/crowdnavpp.py); the defaults are CrowdNav++'s PPO
(docs/crowdnavpp.md). Note the two meanings of "crowdnavpp": ``--policy.type=crowdnavpp`` is the
network, ``--env.preset=crowdnavpp`` the simulator's scene (robot radius 0.3 m, 5 m sensing).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..cli import run_cli
from ..sim.config import CrowdSimConfig
from .config import PPOConfig
from .trainer import PPORunConfig, run_ppo

CONFIG_NAME = "train_ppo_config.json"
POLICY_TYPES = ("crowdnavpp",)


@dataclass
class CrowdNavPPPPOConfig(PPOConfig):
    """CrowdNav++'s PPO (reference arguments.py / ppo.py): one Adam, lr 4e-5, eps 1e-5; 30-step
    rollouts; 5 epochs of 2 minibatches (240 steps = 8 whole 30-step sequences of 16 envs); clip
    0.2; clipped value loss, coefficient 0.5; no entropy bonus; gradient norm 0.5; gamma 0.99,
    GAE lambda 0.95; advantages normalized once over the rollout; timeouts terminal; raw rewards;
    no KL stop and no critic warm-up (the trunk is shared). Class defaults, not a factory: draccus
    builds ``--ppo.*`` from the class's defaults."""

    n_steps: int = 30
    batch_size: int = 240
    update_epochs: int = 5
    actor_lr: float = 4e-5
    critic_lr: float = 4e-5  # unused: one parameter group ("actor")
    clip_ploss_coef: float = 0.2
    vf_coef: float = 0.5
    target_kl: float = 0.0
    reward_scale_running: bool = False
    n_critic_warmup_itr: int = 0
    max_grad_norm: float = 0.5
    adam_eps: float = 1e-5
    clip_vloss: bool = True
    norm_adv: str = "rollout"
    bootstrap_timeouts: bool = False


@dataclass
class PolicyChoice:
    # The policy trained from scratch: crowdnavpp (CrowdNav++'s attention-graph recurrent network,
    # the lerobot plugin lerobot_policy_crowdnavpp). Its sizes are the reference's; its crowd
    # layout (humans, prediction steps) follows --env.
    type: str = "crowdnavpp"
    # Start from this pretrained_model directory of the same type instead of fresh weights.
    path: Path | None = None


@dataclass
class TrainPPOConfig(PPORunConfig):
    policy: PolicyChoice = field(default_factory=PolicyChoice)
    # Envs stepped together by each process (reference: 16 processes).
    num_envs: int = 16
    # Budget in environment steps, all processes together (reference: 10 M for the holonomic robot).
    env_steps: int = 10_000_000
    ppo: CrowdNavPPPPOConfig = field(default_factory=CrowdNavPPPPOConfig)
    # Reference seed.
    seed: int = 425

    def validate(self, world_size: int = 1) -> None:
        super().validate(world_size)
        if self.policy.type not in POLICY_TYPES:
            raise ValueError(f"--policy.type={self.policy.type!r}: PPO from scratch trains {', '.join(POLICY_TYPES)} "
                             "(PDPO is fine-tuned by lerobot-crowdnav-finetune)")


def train_ppo(cfg: TrainPPOConfig) -> dict:
    """One process (rank) of the run (rl/trainer.py ``run_ppo``)."""
    from .crowdnavpp import check_compatible, load_agent, make_agent

    def build_agent(source: Path | None, sim_cfg: CrowdSimConfig):
        agent = make_agent(sim_cfg, cfg.seed) if source is None else load_agent(source)
        check_compatible(agent.policy, sim_cfg)
        return agent

    return run_ppo(cfg, build_agent, cfg.policy.path, command="train_ppo", config_name=CONFIG_NAME,
                   label=f"PPO {cfg.policy.type}", done="trained")


def main(argv: list[str] | None = None) -> None:
    run_cli(TrainPPOConfig, train_ppo, argv, "rerun the same command with --resume=true to continue from the last checkpoint")


if __name__ == "__main__":
    main()
