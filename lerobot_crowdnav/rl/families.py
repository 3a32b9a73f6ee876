"""The policy families that ``lerobot-crowdnav-train-ppo`` trains: a family is a lerobot policy
type with its actor-critic (rl/agent.py) and its PPO recipe. A new family is one module that calls
``register`` when imported (and ``data.hub.register_model_card`` for its hub model card). The
family ``T`` in this package is the module ``rl/T.py``, imported by the first lookup of ``T``
(``crowdnavpp``: rl/crowdnavpp.py), so adding that file is all it takes; a module elsewhere (the
Gaussian MLP of tests/test_rl.py) registers its family when it is imported.
"""

from __future__ import annotations

import importlib
import importlib.util
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


PACKAGE = __package__  # where the module of family T is T.py
REGISTERS = "register(Family("  # what the source of a family module holds


def get(name: str) -> Family:
    """The family ``name``: registered already, else registered by importing its module
    ``<PACKAGE>.<name>``; a clear error when there is none."""
    module = f"{PACKAGE}.{name}"
    if name not in _FAMILIES and name.isidentifier() and importlib.util.find_spec(module) is not None:
        importlib.import_module(module)
    if name not in _FAMILIES:
        raise ValueError(f"--policy.type={name!r}: PPO from scratch trains {', '.join(known())} (the family T is "
                         f"registered by the module {PACKAGE}.T; a pretrained PDPO policy is fine-tuned by "
                         "lerobot-crowdnav-finetune)")
    return _FAMILIES[name]


def known() -> list[str]:
    """The families registered so far and those whose module in ``PACKAGE`` would register one."""
    spec = importlib.util.find_spec(PACKAGE)
    modules = {path.stem for folder in spec.submodule_search_locations for path in Path(folder).glob("*.py")
               if path.resolve() != Path(__file__).resolve() and REGISTERS in path.read_text()}
    return sorted(set(_FAMILIES) | modules)
