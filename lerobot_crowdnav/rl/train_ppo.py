"""PPO from scratch of an actor-critic policy (CrowdNav++ or any registered family):
``lerobot-crowdnav-train-ppo``.

    lerobot-crowdnav-train-ppo --policy.type=crowdnavpp --env.task=CrowdNav-v0 --env.preset=crowdnavpp \\
        --output_dir=outputs/train_ppo/crowdnavpp_original
    lerobot-crowdnav-train-ppo --config_path=configs/rl/crowdnavpp_bounded.yaml [--resume=true]
    accelerate launch --num_processes=2 -m lerobot_crowdnav.rl.train_ppo ...   # DDP, one env batch per process

The run is the shared PPO run (rl/trainer.py: collect, update, validation, checkpoints, resume,
logs, DDP) with the agent of the ``--policy.type`` family (rl/families.py), whose recipe gives the
defaults (CrowdNav++'s: docs/crowdnavpp.md). Note the two meanings of "crowdnavpp":
``--policy.type=crowdnavpp`` is the network, ``--env.preset=crowdnavpp`` the simulator's scene
(robot radius 0.3 m, 5 m sensing).
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass, field
from pathlib import Path

from ..checkpoint_files import TRAIN_PPO_CONFIG
from ..cli import USER_ERRORS, run_cli
from . import families
from .trainer import PPORunConfig, run_ppo

DEFAULT_TYPE = "crowdnavpp"


@dataclass
class PolicyChoice:
    # The policy trained from scratch: a registered family (rl/families.py), by default crowdnavpp
    # (CrowdNav++'s attention-graph recurrent network, the lerobot plugin lerobot_policy_crowdnavpp;
    # its sizes are the reference's, its crowd layout follows --env). The family's recipe gives the
    # defaults of --ppo.*, --num_envs, --env_steps and --seed.
    type: str = DEFAULT_TYPE
    # Start from this pretrained_model directory of the same type instead of fresh weights.
    path: Path | None = None


@dataclass
class TrainPPOConfig(PPORunConfig):
    policy: PolicyChoice = field(default_factory=PolicyChoice)

    def validate(self, world_size: int = 1) -> None:
        super().validate(world_size)
        families.get(self.policy.type)


def config_class(family: families.Family) -> type[TrainPPOConfig]:
    """``TrainPPOConfig`` with ``family``'s recipe as its defaults: draccus builds the flags, and
    the resume check the defaults of settings a saved run lacks, from the class. It keeps the
    name, so that draccus finds the flags' help in the source of its bases."""
    fields = [("policy", PolicyChoice, field(default_factory=lambda: PolicyChoice(family.name))),
              ("ppo", family.ppo, field(default_factory=family.ppo)),
              *((name, type(value), value) for name, value in family.run_defaults.items())]
    return dataclasses.make_dataclass("TrainPPOConfig", fields, bases=(TrainPPOConfig,))


def policy_type(argv: list[str]) -> str:
    """The ``--policy.type`` of ``argv``, else of its ``--config_path`` file, else the default:
    the family whose config class parses the command line."""
    import yaml

    found, args = {}, iter(argv)
    for arg in args:
        key, eq, value = arg.partition("=")
        if key in ("--policy.type", "--config_path"):
            found[key] = value if eq else next(args, "")
    if "--policy.type" in found:
        return found["--policy.type"]
    if "--config_path" in found:
        saved = yaml.safe_load(Path(found["--config_path"]).read_text()) or {}
        return (saved.get("policy") or {}).get("type", DEFAULT_TYPE)
    return DEFAULT_TYPE


def train_ppo(cfg: TrainPPOConfig) -> dict:
    """One process (rank) of the run (rl/trainer.py ``run_ppo``)."""
    family = families.get(cfg.policy.type)
    return run_ppo(cfg, lambda source, sim_cfg: family.build_agent(source, sim_cfg, cfg.seed), cfg.policy.path,
                   command="train_ppo", config_name=TRAIN_PPO_CONFIG, label=f"PPO {family.name}", done="trained")


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        family = families.get(policy_type(argv))
    except USER_ERRORS as e:
        raise SystemExit(f"error: {e}") from None
    run_cli(config_class(family), train_ppo, argv, "rerun the same command with --resume=true to continue from the last checkpoint")


if __name__ == "__main__":
    main()
