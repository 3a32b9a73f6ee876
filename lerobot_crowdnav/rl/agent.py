"""The interface between the PPO loop and a policy: what the trainer may ask of an actor-critic.

An actor-critic is an ``nn.Module`` with

* ``recurrent: bool`` - whether it carries memory across steps (then the update replays whole
  per-env sequences from the rollout's initial memory, CleanRL's ``ppo_atari_lstm``);
* ``initial_memory(num_envs) -> Tensor (B, ...) | None`` - zeros mean "a fresh episode" (the
  loop zeroes the rows of envs whose episode just ended); None for a feed-forward policy;
* ``act(obs, memory, explore, generator) -> Step`` - obs ``(B, D)`` raw env observations
  (float32, the env's units); the action ``(B, A)`` in env units; ``stored``: whatever the policy
  needs to score the decision later, each ``(B, ...)``; the memory after the step;
* ``forward(samples, memory, episode_start) -> Scores`` (what DDP wraps) - samples: the stored
  tensors ``(L, M, ...)`` of M sequences of L steps (flat minibatches: L = 1), ``memory`` their
  initial memory ``(M, ...)`` or None, ``episode_start (L, M)`` where memory restarts;
* ``value(obs, memory) -> Tensor (B,)`` - V of raw observations (bootstraps);
* ``param_groups() -> {"actor": [...], "critic": [...]}`` - one optimizer each.

Everything the env side sees is raw (obs and actions in env units): normalization, chunking or
denoising chains are the actor-critic's own business.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple, Protocol

import torch
from torch import Tensor


class Step(NamedTuple):
    action: Tensor  # (B, A) env units
    stored: dict[str, Tensor]  # each (B, ...): what forward() scores later
    memory: Tensor | None  # (B, ...) after this step


class Scores(NamedTuple):
    """A NamedTuple so that DDP finds its tensors."""

    logp: Tensor  # (L, M, n) log-probability of each of the decision's n scored parts
    value: Tensor  # (L, M)
    entropy: Tensor | None  # (L, M) where the policy has a closed form; None otherwise


class ActorCritic(Protocol):
    recurrent: bool

    def initial_memory(self, num_envs: int) -> Tensor | None: ...

    def act(self, obs: Tensor, memory: Tensor | None, explore: bool, generator: torch.Generator) -> Step: ...

    def forward(self, samples: dict[str, Tensor], memory: Tensor | None, episode_start: Tensor) -> Scores: ...

    def value(self, obs: Tensor, memory: Tensor | None) -> Tensor: ...

    def param_groups(self) -> dict[str, list[torch.nn.Parameter]]: ...


def read_policy_config(path: Path, kind: str, purpose: str):
    """The lerobot config of the ``pretrained_model`` directory ``path`` (device cpu), which must
    hold a ``kind`` policy (plugins registered); a clear error otherwise. ``purpose`` ends the
    wrong-type message (what this command does with it)."""
    import json

    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.utils.import_utils import register_third_party_plugins

    path = Path(path)
    if not (path / "config.json").exists():
        raise FileNotFoundError(f"--policy.path={path}: no config.json (expected a pretrained_model directory)")
    found = json.loads((path / "config.json").read_text()).get("type")
    if found != kind:
        raise ValueError(f"--policy.path={path} holds a {found!r} policy; {purpose}")
    register_third_party_plugins()
    cfg = PreTrainedConfig.from_pretrained(path)
    cfg.device = "cpu"
    return cfg


def check_observation_layout(policy_cfg, sim_cfg) -> None:
    """A policy config (num_humans, prediction_steps, state_dim) must read the env's observations."""
    cfg = policy_cfg
    if (cfg.num_humans, cfg.prediction_steps) != (sim_cfg.num_humans, sim_cfg.prediction_steps) \
            or cfg.state_dim != sim_cfg.obs_dim:
        raise ValueError(f"the policy reads {cfg.state_dim}-float observations ({cfg.num_humans} humans, "
                         f"{cfg.prediction_steps} prediction steps); the env gives {sim_cfg.obs_dim} "
                         f"({sim_cfg.num_humans} humans, {sim_cfg.prediction_steps} prediction steps)")
