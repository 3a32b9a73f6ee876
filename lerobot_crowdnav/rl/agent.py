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
* ``n_parts: int`` - the n of ``Scores.logp``: the parts a decision is scored as (a Gaussian: 1,
  diffusion PPO: K'); the PPO settings give one clip and one advantage weight per part;
* ``param_groups() -> {"actor": [...], "critic": [...]}`` - one optimizer each: "actor" the
  parameters the policy loss trains (with whatever they share with the critic), "critic" (may be
  absent: a shared trunk) those only the value loss trains, the ones a critic warm-up updates;
* ``save(path)`` - write the policy as a lerobot ``pretrained_model`` directory (what the next
  run's or ``lerobot-crowdnav-eval``'s ``--policy.path`` loads), plus any RL-side state it needs.

``check_actor_critic`` checks an agent against this where a run builds it.

Everything the env side sees is raw (obs and actions in env units): normalization, chunking or
denoising chains are the actor-critic's own business.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple, Protocol

import torch
from torch import Tensor

from ..checkpoint_files import POLICY_CONFIG
from ..layout import check_sentinel


class Step(NamedTuple):
    action: Tensor  # (B, A) env units
    stored: dict[str, Tensor]  # each (B, ...): what forward() scores later
    memory: Tensor | None  # (B, ...) after this step


class Scores(NamedTuple):
    """A NamedTuple so that DDP finds its tensors."""

    logp: Tensor  # (L, M, n) log-probability of each of the decision's n scored parts
    value: Tensor  # (L, M)
    entropy: Tensor | None  # (L, M) where the policy has a closed form; None otherwise


ACTOR, CRITIC = "actor", "critic"  # the parameter groups (one optimizer each)


class ActorCritic(Protocol):
    recurrent: bool
    n_parts: int

    def initial_memory(self, num_envs: int) -> Tensor | None: ...

    def act(self, obs: Tensor, memory: Tensor | None, explore: bool, generator: torch.Generator) -> Step: ...

    def forward(self, samples: dict[str, Tensor], memory: Tensor | None, episode_start: Tensor) -> Scores: ...

    def value(self, obs: Tensor, memory: Tensor | None) -> Tensor: ...

    def param_groups(self) -> dict[str, list[torch.nn.Parameter]]: ...

    def save(self, path: Path) -> None: ...


def check_actor_critic(agent, ppo) -> None:
    """``agent`` has every member of ``ActorCritic``, its parameter groups are "actor" and
    optionally "critic", and the PPO settings ``ppo`` fit it (one clip and weight per scored part;
    a critic warm-up needs critic-only parameters): a clear error otherwise, before any rollout."""
    members = [*ActorCritic.__annotations__, *(n for n in vars(ActorCritic) if callable(getattr(ActorCritic, n))
                                              and not n.startswith("_"))]
    if missing := [m for m in members if not hasattr(agent, m)]:
        raise TypeError(f"{type(agent).__name__} is not an actor-critic (rl/agent.py): it lacks {', '.join(missing)}")
    groups = agent.param_groups()
    if ACTOR not in groups or not set(groups) <= {ACTOR, CRITIC}:
        raise TypeError(f"{type(agent).__name__}.param_groups() gives {sorted(groups)}: expected {ACTOR!r} and "
                        f"optionally {CRITIC!r}")
    for name, per_part in (("clip_per_part", ppo.clip_per_part()), ("advantage_weights", ppo.advantage_weights())):
        if per_part.shape != (agent.n_parts,):
            raise ValueError(f"the PPO settings' {name} has shape {per_part.shape}; {type(agent).__name__} scores a "
                             f"decision as {agent.n_parts} part(s)")
    if ppo.n_critic_warmup_itr and CRITIC not in groups:
        raise ValueError(f"--ppo.n_critic_warmup_itr={ppo.n_critic_warmup_itr}: {type(agent).__name__} has no "
                         "critic-only parameters (actor and critic share them), so a warm-up would train nothing; "
                         "set it to 0")


def read_policy_config(path: Path, kind: str, purpose: str):
    """The lerobot config of the ``pretrained_model`` directory ``path`` (device cpu), which must
    hold a ``kind`` policy (plugins registered); a clear error otherwise. ``purpose`` ends the
    wrong-type message (what this command does with it)."""
    import json

    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.utils.import_utils import register_third_party_plugins

    path = Path(path)
    if not (path / POLICY_CONFIG).exists():
        raise FileNotFoundError(f"--policy.path={path}: no {POLICY_CONFIG} (expected a pretrained_model directory)")
    found = json.loads((path / POLICY_CONFIG).read_text()).get("type")
    if found != kind:
        raise ValueError(f"--policy.path={path} holds a {found!r} policy; {purpose}")
    register_third_party_plugins()
    cfg = PreTrainedConfig.from_pretrained(path)
    cfg.device = "cpu"
    return cfg


def check_observation_layout(policy_cfg, sim_cfg) -> None:
    """A policy config (num_humans, prediction_steps, state_dim, a sentinel it knows) must read
    the env's observations."""
    cfg = policy_cfg
    if (cfg.num_humans, cfg.prediction_steps) != (sim_cfg.num_humans, sim_cfg.prediction_steps) \
            or cfg.state_dim != sim_cfg.obs_dim:
        raise ValueError(f"the policy reads {cfg.state_dim}-float observations ({cfg.num_humans} humans, "
                         f"{cfg.prediction_steps} prediction steps); the env gives {sim_cfg.obs_dim} "
                         f"({sim_cfg.num_humans} humans, {sim_cfg.prediction_steps} prediction steps)")
    check_sentinel(cfg, sim_cfg.sentinel)
