"""The PPO loop is policy-agnostic: a tiny Gaussian actor-critic, written here against the
protocol of lerobot_crowdnav.rl.agent and touching nothing of the trainer, learns a trivial task
with the same collect/update code as diffusion PPO; its GRU variant trains on per-env sequences
and learns what a feed-forward policy cannot (remember a cue)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from accelerate import Accelerator
from torch import nn

from lerobot_crowdnav.rl.agent import Scores, Step
from lerobot_crowdnav.rl.config import PPOConfig
from lerobot_crowdnav.rl.loop import Collector, update
from lerobot_crowdnav.rl.ppo import RunningRewardScaler

HORIZON = 4


class CueEnv:
    """A batched env: the goal g = +-1 is shown at an episode's first step (``cue_always``: at
    every step); obs = [cue, t / H]; reward -(a - g)^2 per step; episodes time out after H steps."""

    def __init__(self, num_envs: int, cue_always: bool):
        self.num_envs, self.cue_always = num_envs, cue_always

    def _obs(self) -> np.ndarray:
        cue = self.g if self.cue_always else np.where(self.t == 0, self.g, 0.0)
        return np.stack([cue, self.t / HORIZON], axis=1).astype(np.float32)

    def reset(self, seed: int):
        self.rng = np.random.default_rng(seed)
        self.g = self.rng.choice([-1.0, 1.0], self.num_envs)
        self.t = np.zeros(self.num_envs)
        return self._obs(), {}

    def step(self, action: np.ndarray):
        reward = -((action[:, 0] - self.g) ** 2)
        self.t += 1
        trunc = self.t >= HORIZON
        info = {"final_obs": self._obs()}
        self.g = np.where(trunc, self.rng.choice([-1.0, 1.0], self.num_envs), self.g)
        self.t[trunc] = 0
        return self._obs(), reward, np.zeros(self.num_envs, bool), trunc, info


class GaussianActorCritic(nn.Module):
    """A Gaussian policy and a value head on a shared MLP (or GRU, ``recurrent``) core."""

    def __init__(self, obs_dim: int, recurrent: bool, hidden: int = 32):
        super().__init__()
        self.recurrent, self.hidden = recurrent, hidden
        self.core = nn.GRUCell(obs_dim, hidden) if recurrent else nn.Sequential(nn.Linear(obs_dim, hidden), nn.Tanh())
        self.mu, self.value_head = nn.Linear(hidden, 1), nn.Linear(hidden, 1)
        self.log_std = nn.Parameter(torch.full((1,), -0.5))

    def initial_memory(self, num_envs: int):
        return torch.zeros(num_envs, self.hidden) if self.recurrent else None

    def param_groups(self):
        return {"actor": [*self.core.parameters(), *self.mu.parameters(), self.log_std],
                "critic": list(self.value_head.parameters())}

    def _features(self, obs, memory, starts):
        """obs (L, M, D), starts (L, M) -> features (L, M, hidden) and the last memory."""
        if not self.recurrent:
            return self.core(obs), None
        out = []
        for t in range(obs.shape[0]):
            memory = self.core(obs[t], memory * ~starts[t, :, None])
            out.append(memory)
        return torch.stack(out), memory

    @torch.no_grad()
    def act(self, obs, memory, explore, generator):
        h, memory = self._features(obs[None], memory, torch.zeros(1, obs.shape[0], dtype=torch.bool))
        action = self.mu(h[0])
        if explore:
            action = action + self.log_std.exp() * torch.randn(action.shape, generator=generator)
        return Step(action, {"obs": obs, "action": action}, memory)

    def forward(self, samples, memory, episode_start):
        h, _ = self._features(samples["obs"], memory, episode_start)
        dist = torch.distributions.Normal(self.mu(h), self.log_std.exp())
        return Scores(dist.log_prob(samples["action"]), self.value_head(h).squeeze(-1), dist.entropy().sum(-1))

    @torch.no_grad()
    def value(self, obs, memory):
        h, _ = self._features(obs[None], memory, torch.zeros(1, obs.shape[0], dtype=torch.bool))
        return self.value_head(h[0]).squeeze(-1)


def deterministic_return(agent, cue_always: bool, n: int = 256) -> float:
    """Mean reward per step of one episode per env, without exploration noise."""
    env = CueEnv(n, cue_always)
    obs, _ = env.reset(seed=123)
    memory, total = agent.initial_memory(n), 0.0
    for _ in range(HORIZON):
        step = agent.act(torch.as_tensor(obs), memory, False, None)
        obs, reward, *_ = env.step(step.action.numpy())
        memory, total = step.memory, total + reward.mean()
    return total / HORIZON


@pytest.mark.parametrize("recurrent", [False, True], ids=["mlp_flat_minibatches", "gru_sequence_minibatches"])
def test_a_second_actor_critic_learns_with_the_same_ppo_loop(recurrent):
    torch.manual_seed(0)
    cue_always = not recurrent  # the GRU must remember the cue: a feed-forward policy cannot
    agent = GaussianActorCritic(2, recurrent)
    cfg = PPOConfig(n_steps=16, batch_size=128, update_epochs=4, actor_lr=3e-3, critic_lr=3e-3, gamma=0.9,
                    clip_ploss_coef=0.2, target_kl=0.0, n_critic_warmup_itr=1)
    env = CueEnv(32, cue_always)
    collector = Collector(env, agent, RunningRewardScaler(env.num_envs, cfg.gamma), torch.Generator().manual_seed(0))
    collector.reset(seed=0)
    optimizers = {name: torch.optim.Adam(params, lr=cfg.actor_lr) for name, params in agent.param_groups().items()}
    rng, acc = np.random.default_rng(0), Accelerator(cpu=True)
    before = deterministic_return(agent, cue_always)
    for iteration in range(60):
        ro = collector.collect(agent, cfg.n_steps)
        assert len(ro.timeouts) == ro.final_obs.shape[0] > 0
        if recurrent:
            assert ro.memory0.shape == (32, agent.hidden) and ro.starts[0].any()
        stats = update(agent, agent, ro, cfg, optimizers, rng, acc, train_actor=iteration >= cfg.n_critic_warmup_itr)
    after = deterministic_return(agent, cue_always)
    # Remembering the cue is worth more than the best memoryless policy (a = 0 after the cue step: -0.75).
    assert after > max(before + 0.4, -0.75 + 0.3 if recurrent else -0.2), (before, after)
    assert stats["explained_variance"] > 0.2 and "entropy" in stats
