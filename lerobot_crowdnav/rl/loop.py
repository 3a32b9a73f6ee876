"""The PPO loop for any actor-critic (rl/agent.py), in the order it runs: collect a rollout,
score it under the pre-update weights, compute advantages, update (CleanRL's
``ppo_continuous_action.py``; per-env sequences as in ``ppo_atari_lstm.py`` for recurrent policies).

Shapes: T = n_steps, B = num_envs, D = observation size, n = scored parts per decision (1 for a
Gaussian policy, K' denoising steps for DPPO), L x M = a minibatch of M columns of L steps
(flat: L = 1 and a column is one env step; recurrent: L = T and a column is one env's sequence).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..sim.engine import EVENT_NAMES
from .agent import CRITIC
from .config import PPOConfig
from .ppo import RunningRewardScaler, explained_variance, gae, normalize_advantages, ppo_losses


@dataclass
class Rollout:
    stored: dict[str, Tensor]  # each (T, B, ...): what act() returned to score later
    memory0: Tensor | None  # (B, ...) memory before step 0
    starts: np.ndarray  # (T, B) observation t begins an episode (memory was zeroed)
    rewards: np.ndarray  # (T, B) raw env rewards
    scaled_rewards: np.ndarray  # (T, B) what the critic learns
    terminated: np.ndarray  # (T, B)
    done: np.ndarray  # (T, B) terminated or truncated
    next_obs: Tensor  # (B, D) raw observation after the last step
    next_memory: Tensor | None  # (B, ...)
    timeouts: list[tuple[int, int]]  # (t, b) of the episodes that ended by timeout
    final_obs: Tensor  # (F, D) their true final observations (not the next episode's first)
    final_memory: Tensor | None  # (F, ...)
    episodes: list[dict]  # event, return, length of the episodes that ended

    def digest(self) -> str:
        """Fingerprint of the data an update sees (reproducibility checks across resumes)."""
        h = hashlib.sha256()
        for a in (*(v.cpu().numpy() for v in self.stored.values()), self.rewards, self.done):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()[:16]


# -- 1. collect ----------------------------------------------------------------------------------
class Collector:
    """Steps a batched env with an actor-critic, carrying the observations, memory, reward
    scaler and sampling noise from one iteration to the next (all of it resumable)."""

    def __init__(self, env, agent, scaler: RunningRewardScaler | None, generator: torch.Generator):
        self.env, self.scaler, self.generator = env, scaler, generator
        self.obs: np.ndarray | None = None  # (B, D)
        self.memory = agent.initial_memory(env.num_envs)
        self.starts = np.ones(env.num_envs, bool)

    def reset(self, seed: int) -> None:
        self.obs, _ = self.env.reset(seed=seed)

    @torch.no_grad()
    def collect(self, agent, n_steps: int) -> Rollout:
        T, B = n_steps, self.env.num_envs
        memory0, starts = self.memory, np.zeros((T, B), bool)
        stored: list[dict[str, Tensor]] = []
        rewards, scaled = np.zeros((T, B)), np.zeros((T, B))
        terminated, done = np.zeros((T, B), bool), np.zeros((T, B), bool)
        timeouts, final_obs, final_memory, episodes = [], [], [], []
        for t in range(T):
            starts[t] = self.starts
            step = agent.act(torch.as_tensor(self.obs, dtype=torch.float32), self.memory, True, self.generator)
            stored.append(step.stored)
            self.obs, reward, term, trunc, info = self.env.step(step.action.cpu().numpy().astype(np.float64))
            rewards[t], terminated[t], done[t] = reward, term, term | trunc
            scaled[t] = self.scaler(reward, done[t]) if self.scaler is not None else reward
            for b in np.flatnonzero(trunc):  # bootstrap a timeout from its true final observation
                timeouts.append((t, int(b)))
                final_obs.append(info["final_obs"][b])
                if step.memory is not None:
                    final_memory.append(step.memory[b])
            if "final_info" in info:
                fi = info["final_info"]
                for b in np.flatnonzero(info["_final_info"]):
                    episodes.append({"event": EVENT_NAMES[int(fi["event"][b])], "return": float(fi["return"][b]),
                                     "prediction_penalty": float(fi["prediction_penalty"][b]),
                                     "length": int(fi["length"][b])})
            self.starts = done[t].copy()
            self.memory = restart_memory(step.memory, self.starts)
        dim = self.obs.shape[1]
        return Rollout(
            stored={k: torch.stack([s[k] for s in stored]) for k in stored[0]}, memory0=memory0, starts=starts,
            rewards=rewards, scaled_rewards=scaled, terminated=terminated, done=done,
            next_obs=torch.as_tensor(self.obs, dtype=torch.float32), next_memory=self.memory, timeouts=timeouts,
            final_obs=torch.as_tensor(np.array(final_obs, np.float32).reshape(-1, dim)),
            final_memory=torch.stack(final_memory) if final_memory else None, episodes=episodes)

    def state_dict(self) -> dict:
        return {"torch": self.generator.get_state().tolist(), "scaler": self.scaler.state_dict() if self.scaler else None,
                "starts": self.starts.tolist(), "memory": None if self.memory is None else self.memory.tolist()}

    def load_state_dict(self, state: dict) -> None:
        """Env and observations come from ``env.load_state_dict``; this restores the rest."""
        self.obs = self.env.sim.obs.copy()
        saved = torch.tensor(state["torch"], dtype=torch.uint8)
        if saved.numel() == self.generator.get_state().numel():
            self.generator.set_state(saved)
        else:  # saved on another device type (CPU and CUDA generators differ): a seed derived from it
            self.generator.manual_seed(int.from_bytes(hashlib.sha256(saved.numpy().tobytes()).digest()[:8], "little"))
        if self.scaler is not None:
            self.scaler.load_state_dict(state["scaler"])
        self.starts = np.asarray(state.get("starts", self.starts), bool)
        if state.get("memory") is not None:
            self.memory = torch.tensor(state["memory"], dtype=self.memory.dtype, device=self.memory.device)


def restart_memory(memory: Tensor | None, starts: np.ndarray) -> Tensor | None:
    """Zero the memory of envs whose episode just ended (zeros = a fresh episode)."""
    if memory is None or not starts.any():
        return memory
    keep = torch.as_tensor(~starts, device=memory.device).view(-1, *([1] * (memory.dim() - 1)))
    return memory * keep


# -- 2. score and advantages -----------------------------------------------------------------------
@dataclass
class Columns:
    """A rollout seen as N columns of L steps: the unit a minibatch samples."""

    samples: dict[str, Tensor]  # each (L, N, ...)
    memory: Tensor | None  # (N, ...) memory at each column's first step
    starts: Tensor  # (L, N) bool

    @staticmethod
    def of(ro: Rollout, recurrent: bool, device: torch.device) -> Columns:
        starts = torch.as_tensor(ro.starts, device=device)
        if recurrent:  # one column per env: its whole sequence
            return Columns({k: v.to(device) for k, v in ro.stored.items()}, ro.memory0, starts)
        flat = lambda x: x.reshape(1, -1, *x.shape[2:]).to(device)  # noqa: E731  (T, B, ...) -> (1, T*B, ...)
        return Columns({k: flat(v) for k, v in ro.stored.items()}, None, flat(starts))

    @property
    def n(self) -> int:
        return self.starts.shape[1]

    def __getitem__(self, idx: Tensor) -> tuple[dict[str, Tensor], Tensor | None, Tensor]:
        return ({k: v[:, idx] for k, v in self.samples.items()},
                None if self.memory is None else self.memory[idx], self.starts[:, idx])


def bootstrap_values(agent, ro: Rollout, values: np.ndarray) -> np.ndarray:
    """V of the state each step reached, ``(T, B)``: the next step's value, after the last step
    V(next_obs), and for a timeout V of its true final observation (one batched pass)."""
    B = values.shape[1]
    memory = None if ro.next_memory is None else torch.cat([ro.next_memory, *(
        [ro.final_memory] if ro.final_memory is not None else [])])
    with torch.no_grad():
        v_boot = agent.value(torch.cat([ro.next_obs, ro.final_obs]), memory).cpu().numpy()  # (B + F,)
    next_values = np.concatenate([values[1:], v_boot[None, :B]], axis=0)
    for (t, b), value in zip(ro.timeouts, v_boot[B:], strict=True):
        next_values[t, b] = value
    return next_values


def advantages(ro: Rollout, values: np.ndarray, next_values: np.ndarray, cfg: PPOConfig) -> tuple[np.ndarray, np.ndarray]:
    """GAE on the (T, B) grid: terminations do not bootstrap; timeouts bootstrap from their final
    observation's value, or with ``bootstrap_timeouts=False`` are terminal too (CrowdNav++)."""
    terminal = ro.terminated if cfg.bootstrap_timeouts else ro.done
    return gae(ro.scaled_rewards, values, next_values, terminal.astype(float), ro.done.astype(float), cfg.gamma,
               cfg.gae_lambda)


# -- 3. update -------------------------------------------------------------------------------------
def update(model, agent, ro: Rollout, cfg: PPOConfig, optimizers: dict[str, torch.optim.Optimizer],
           rng: np.random.Generator, accelerator, train_actor: bool) -> dict[str, float]:
    """PPO epochs over one rollout. ``model`` is the actor-critic as the accelerator prepared it
    (DDP-wrapped across processes), ``agent`` the same module unwrapped."""
    device = accelerator.device
    T, B = ro.rewards.shape
    cols = Columns.of(ro, agent.recurrent, device)
    mb = max(1, cfg.batch_size // T) if agent.recurrent else cfg.batch_size  # columns per minibatch
    clip = torch.tensor(cfg.clip_per_part(), dtype=torch.float32, device=device)  # (n,)
    weights = torch.tensor(cfg.advantage_weights(), dtype=torch.float32, device=device)  # (n,)

    # Old log-probabilities (L, N, n) and values (L, N) under the pre-update weights, computed over
    # the first epoch's minibatch partition with autograd on (no_grad would switch attention to
    # its fused kernel): the first minibatch's ratio is then exactly 1.
    first_perm = rng.permutation(cols.n)
    old_logp = values = None
    for i in range(0, cols.n, mb):
        idx = torch.as_tensor(first_perm[i:i + mb], device=device)
        scores = agent(*cols[idx])
        if old_logp is None:
            if scores.logp.shape[-1] != agent.n_parts:  # the clip and weights above have n_parts entries
                raise ValueError(f"{type(agent).__name__} scored a decision as {scores.logp.shape[-1]} parts, "
                                 f"not its n_parts={agent.n_parts}")
            old_logp = torch.empty(scores.logp.shape[0], cols.n, scores.logp.shape[2], device=device)
            values = torch.empty(scores.value.shape[0], cols.n, device=device)
        old_logp[:, idx], values[:, idx] = scores.logp.detach(), scores.value.detach()

    # GAE on the (T, B) grid; terminations do not bootstrap, timeouts bootstrap from their final obs.
    v = values.cpu().numpy().reshape(T, B)
    adv, ret = advantages(ro, v, bootstrap_values(agent, ro, v), cfg)
    adv_t = torch.as_tensor(adv, dtype=torch.float32, device=device).reshape(values.shape)  # (L, N)
    per_minibatch = cfg.norm_adv == "minibatch"
    if not per_minibatch:  # once over this process's rollout (CrowdNav++: eps 1e-5)
        adv_t = normalize_advantages(adv_t, 1e-5)
    ret_t = torch.as_tensor(ret, dtype=torch.float32, device=device).reshape(values.shape)

    stats: dict[str, list[float]] = {}
    epochs_done, stop = 0, False
    for epoch in range(cfg.update_epochs):
        perm = first_perm if epoch == 0 else rng.permutation(cols.n)
        for start in range(0, cols.n - mb + 1, mb):
            idx = torch.as_tensor(perm[start:start + mb], device=device)
            new = model(*cols[idx])
            flat = lambda x: x.reshape(-1, *x.shape[2:])  # noqa: E731  (L, M, ...) -> (L*M, ...)
            losses = ppo_losses(flat(new.logp), flat(old_logp[:, idx]), flat(adv_t[:, idx]), clip, weights,
                                flat(new.value), flat(ret_t[:, idx]), old_values=flat(values[:, idx]),
                                value_clip=cfg.clip_ploss_coef if cfg.clip_vloss else None, normalize=per_minibatch)
            # During the critic warm-up the policy loss has zero weight, so that every parameter
            # still gets a (zero) gradient, as DDP requires.
            loss = (1.0 if train_actor else 0.0) * losses["policy_loss"] + cfg.vf_coef * losses["value_loss"]
            for opt in optimizers.values():
                opt.zero_grad(set_to_none=True)
            accelerator.backward(loss)
            if cfg.max_grad_norm:
                for opt in optimizers.values():
                    accelerator.clip_grad_norm_([p for g in opt.param_groups for p in g["params"]], cfg.max_grad_norm)
            for name, opt in optimizers.items():
                if train_actor or name == CRITIC:
                    opt.step()
            if new.entropy is not None:
                losses["entropy"] = new.entropy.mean().detach()
            for k, val in losses.items():
                stats.setdefault(k, []).append(float(val.detach()))
            kl = accelerator.reduce(losses["approx_kl"].detach().clone(), reduction="mean")
            if cfg.target_kl and float(kl) > cfg.target_kl:
                stop = True  # like DPPO: the step that crossed the target is kept
                break
        epochs_done += 1
        if stop:
            break
    out = {f"loss/{k}" if k.endswith("loss") else k: float(np.mean(val)) for k, val in stats.items()}
    out["update_epochs"] = epochs_done
    out["explained_variance"] = explained_variance(v.reshape(-1), ret.reshape(-1))
    out["critic_warmup"] = float(not train_actor)
    return out
