"""The policy families that ``lerobot-crowdnav-train-ppo`` trains: a family is a lerobot policy
type with its actor-critic (rl/agent.py) and its PPO recipe. A new family is one module that calls
``register`` when imported (and ``data.hub.register_model_card`` for its hub model card); the
built-in one (``crowdnavpp``) registers on the first lookup.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from torch import nn

from ..sim.config import CrowdSimConfig
from .config import PPOConfig


@dataclass(frozen=True)
class Family:
    # --policy.type: the "type" in the policy's config.json.
    name: str
    # build_agent(source, sim_cfg, seed): the actor-critic on cpu, read from a pretrained_model
    # directory or, with source None, fresh (initialized from seed), checked against the env.
    build_agent: Callable[[Path | None, CrowdSimConfig, int], nn.Module]
    # The family's PPO recipe: the class whose defaults are the --ppo.* defaults.
    ppo: type[PPOConfig] = PPOConfig
    # Defaults of the run's other settings (num_envs, env_steps, seed, ...).
    run_defaults: dict = field(default_factory=dict)


_FAMILIES: dict[str, Family] = {}


def register(family: Family) -> Family:
    _FAMILIES[family.name] = family
    return family


def get(name: str) -> Family:
    from . import crowdnavpp  # noqa: F401  (registers the built-in family)

    if name not in _FAMILIES:
        raise ValueError(f"--policy.type={name!r}: PPO from scratch trains {', '.join(sorted(_FAMILIES))} "
                         "(a pretrained PDPO policy is fine-tuned by lerobot-crowdnav-finetune)")
    return _FAMILIES[name]
