"""PPO arithmetic (CleanRL's PPO, with DPPO's per-denoising-step extensions), independent of
environments and networks.

Conventions: arrays ``(T, B)`` are time-major rollouts of B envs. A decision (one env step's
action) may be scored as ``n`` parts: n = 1 for a Gaussian policy, n = K' fine-tuned denoising
steps for a diffusion policy (index ``i = 0`` the noisiest, ``i = K'-1`` the final one).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor


class RunningRewardScaler:
    """Rewards divided by a running std of each env's discounted return (no mean subtraction),
    then clipped to +-clip: DPPO's ``reward_scale_running``."""

    def __init__(self, num_envs: int, gamma: float, clip: float = 10.0, eps: float = 1e-8):
        self.gamma, self.clip, self.eps = gamma, clip, eps
        self.ret = np.zeros(num_envs)
        self.mean, self.var, self.count = 0.0, 1.0, 1e-4

    def _update(self, x: np.ndarray) -> None:
        """Chan et al.'s parallel update of the running mean and variance."""
        b_mean, b_var, b_count = float(x.mean()), float(x.var()), x.size
        delta, total = b_mean - self.mean, self.count + b_count
        m2 = self.var * self.count + b_var * b_count + delta**2 * self.count * b_count / total
        self.mean, self.var, self.count = self.mean + delta * b_count / total, m2 / total, total

    def __call__(self, reward: np.ndarray, done: np.ndarray) -> np.ndarray:
        """Scale one step's rewards ``(B,)``; ``done`` restarts the return of the ended episodes."""
        self.ret = self.ret * self.gamma + reward
        self._update(self.ret)
        scaled = np.clip(reward / math.sqrt(self.var + self.eps), -self.clip, self.clip)
        self.ret[done] = 0.0
        return scaled

    def state_dict(self) -> dict:
        return {"ret": self.ret.tolist(), "mean": self.mean, "var": self.var, "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        ret = np.asarray(state["ret"], dtype=np.float64)
        if ret.shape != self.ret.shape:
            raise ValueError(f"reward scaler for {ret.shape[0]} envs, this run has {self.ret.shape[0]}")
        self.ret, self.mean, self.var, self.count = ret, state["mean"], state["var"], state["count"]


def gae(rewards: np.ndarray, values: np.ndarray, next_values: np.ndarray, terminated: np.ndarray,
        done: np.ndarray, gamma: float, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """Generalized advantage estimation over a ``(T, B)`` rollout; returns (advantages, returns).

    ``next_values[t]`` = V of the state reached by step t (for an episode that ended at t: its
    final observation, not the next episode's first). A termination (success, collision) does
    not bootstrap; a truncation (timeout) bootstraps from ``next_values``; both stop the recursion.
    """
    adv = np.zeros_like(rewards, dtype=np.float64)
    last = np.zeros(rewards.shape[1])
    for t in reversed(range(rewards.shape[0])):
        delta = rewards[t] + gamma * next_values[t] * (1.0 - terminated[t]) - values[t]
        last = delta + gamma * lam * (1.0 - done[t]) * last
        adv[t] = last
    return adv, adv + values


def clip_coefficients(ft_steps: int, base: float, clip: float, rate: float) -> np.ndarray:
    """PPO clip coefficient of each fine-tuned denoising step, ``(K',)``: from ``base`` at the
    noisiest (i = 0) to ``clip`` at the final step, growing like ``exp(rate * i / (K'-1))``
    (linearly at rate 0, the exponential's limit)."""
    if ft_steps == 1:
        return np.array([clip])
    i = np.arange(ft_steps) / (ft_steps - 1)
    if rate == 0:
        return base + (clip - base) * i
    return base + (clip - base) * (np.exp(rate * i) - 1) / (math.exp(rate) - 1)


def denoising_discounts(ft_steps: int, gamma_denoising: float) -> np.ndarray:
    """Advantage weight of denoising step i, ``gamma_denoising ** (K'-1-i)``, ``(K',)``."""
    return gamma_denoising ** (ft_steps - 1 - np.arange(ft_steps, dtype=np.float64))


def normalize_advantages(advantages: Tensor, eps: float = 1e-8) -> Tensor:
    """(A - mean) / (std + eps) over all of ``advantages``."""
    return (advantages - advantages.mean()) / (advantages.std() + eps)


def ppo_losses(new_logp: Tensor, old_logp: Tensor, advantages: Tensor, clip: Tensor, discount: Tensor,
               values: Tensor, returns: Tensor, old_values: Tensor | None = None, value_clip: float | None = None,
               normalize: bool = True) -> dict[str, Tensor]:
    """PPO losses for a minibatch of env steps ``(M,)`` whose decisions are scored as n parts
    ``(M, n)``: clipped surrogate with a per-part clip ``(n,)`` and advantage weight ``(n,)``
    (DPPO's denoising discount; 1 for n = 1) on per-minibatch normalized advantages (``normalize``;
    False: the advantages come normalized over the rollout), and ``0.5 (V - return)^2``, or with
    ``value_clip`` and the pre-update values ``old_values`` the clipped value loss of OpenAI
    baselines / CrowdNav++: ``0.5 max((V - R)^2, (V_old + clamp(V - V_old, +-value_clip) - R)^2)``.
    Also the diagnostics (no gradient)."""
    adv = normalize_advantages(advantages) if normalize else advantages
    adv = adv[:, None] * discount[None]  # (M, n)
    logratio = new_logp - old_logp
    ratio = logratio.exp()
    policy_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - clip, 1 + clip)).mean()
    if value_clip is None:
        value_loss = 0.5 * ((values - returns) ** 2).mean()
    else:
        clipped = old_values + (values - old_values).clamp(-value_clip, value_clip)
        value_loss = 0.5 * torch.max((values - returns) ** 2, (clipped - returns) ** 2).mean()
    with torch.no_grad():
        approx_kl = ((ratio - 1) - logratio).mean()
        clipfrac = ((ratio - 1).abs() > clip).float().mean()
    return {"policy_loss": policy_loss, "value_loss": value_loss, "approx_kl": approx_kl,
            "clipfrac": clipfrac, "ratio": ratio.detach().mean()}


def explained_variance(pred: np.ndarray, target: np.ndarray) -> float:
    """1 - Var[target - pred] / Var[target] (NaN when the targets are constant)."""
    var = np.var(target)
    return float("nan") if var == 0 else float(1 - np.var(target - pred) / var)
