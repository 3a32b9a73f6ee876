"""CrowdNav++ as an actor-critic for the PPO loop (rl/agent.py): how an action is sampled and
scored. The network is the plugin's (``lerobot_policy_crowdnavpp``); this side adds the Gaussian
exploration, the sequence scoring and reading/writing training checkpoints.

    stored["obs"]    (B, 269)   raw observation.state (the policy's processors are identity)
    stored["action"] (B, 2)     the sampled velocity in m/s, unclipped (the env clips it by norm)
    memory           (B, 128)   the node GRU's state; zeros = a fresh episode
    Scores.logp      (L, M, 1)  log N(action; mean, exp(log_std)^2), summed over the 2 dims
    Scores.value     (L, M)     V from the critic head on the shared trunk
    Scores.entropy   (L, M)     of the Gaussian, summed over the 2 dims

Actor and critic share the trunk (robot embedding, attentions, GRU), so there is one parameter
group, "actor": one Adam and one global gradient-norm clip, as the reference trains it (no
critic-only parameters, so a critic warm-up is refused: ``n_critic_warmup_itr=0``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from lerobot_policy_crowdnavpp import CrowdNavPPConfig, CrowdNavPPPolicy
from torch import Tensor, nn

from ..sim.config import CrowdSimConfig
from .agent import Scores, Step, check_observation_layout, read_policy_config
from .config import PPOConfig
from .families import Family, register


# Class defaults, not a factory: draccus builds ``--ppo.*`` from the class's defaults.
@dataclass
class CrowdNavPPPPOConfig(PPOConfig):
    """CrowdNav++'s PPO (reference arguments.py / ppo.py): one Adam, lr 4e-5, eps 1e-5; 30-step
    rollouts; 5 epochs of 2 minibatches (240 steps = 8 whole 30-step sequences of 16 envs); clip
    0.2; clipped value loss, coefficient 0.5; no entropy bonus; gradient norm 0.5; gamma 0.99,
    GAE lambda 0.95; advantages normalized once over the rollout; timeouts terminal; raw rewards;
    no KL stop and no critic warm-up (the trunk is shared)."""

    # Steps each env takes per iteration (the reference: num_steps 30).
    n_steps: int = 30
    # Env steps per minibatch: batch_size // n_steps whole env sequences (the reference: 16 envs / 2 minibatches).
    batch_size: int = 240
    # Passes over the iteration's data (the reference: ppo_epoch 5).
    update_epochs: int = 5
    # Adam learning rate of the whole network (the reference: 4e-5).
    actor_lr: float = 4e-5
    # Unused: the network is one parameter group ("actor").
    critic_lr: float = 4e-5
    # PPO clip of the probability ratio (the reference: 0.2).
    clip_ploss_coef: float = 0.2
    # Value-loss coefficient (the reference: 0.5).
    vf_coef: float = 0.5
    # KL early stop (0: never, as the reference).
    target_kl: float = 0.0
    # Scale rewards by a running std of the discounted return (false: raw rewards, as the reference).
    reward_scale_running: bool = False
    # The clip of the scaled rewards (only with --ppo.reward_scale_running=true).
    reward_clip: float = 10.0
    # Critic-only iterations before the actor trains (0: none, as the reference: the trunk is shared).
    n_critic_warmup_itr: int = 0
    # AdamW weight decay of the network (0: plain Adam, as the reference).
    weight_decay: float = 0.0
    # Gradient-norm clip (the reference: 0.5).
    max_grad_norm: float = 0.5
    # Adam's epsilon (the reference: 1e-5).
    adam_eps: float = 1e-5
    # Clipped value loss (the reference: use_clipped_value_loss).
    clip_vloss: bool = True
    # Where advantages are normalized: minibatch | rollout (the reference: once over the whole rollout).
    norm_adv: str = "rollout"
    # Bootstrap the value at timeouts (false: a timeout ends the return like other terminations, as the reference).
    bootstrap_timeouts: bool = False


class CrowdNavPPAgent(nn.Module):
    """The actor-critic protocol for a CrowdNav++ policy. Recurrent."""

    recurrent, n_parts = True, 1

    def __init__(self, policy: CrowdNavPPPolicy):
        super().__init__()
        self.policy = policy

    @property
    def net(self):
        return self.policy.net

    def initial_memory(self, num_envs: int) -> Tensor:
        return self.net.initial_memory(num_envs)

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        return {"actor": list(self.policy.parameters())}

    def _dist(self, mean: Tensor) -> torch.distributions.Normal:
        return torch.distributions.Normal(mean, self.net.log_std.exp())

    @torch.no_grad()
    def act(self, obs: Tensor, memory: Tensor, explore: bool, generator: torch.Generator) -> Step:
        """Exploring: mean + exp(log_std) * noise; otherwise the mean (the reference's
        deterministic evaluation). The action is in m/s, on cpu."""
        obs = obs.to(self.net.log_std.device)
        mean, _, memory = self.net.step(obs, memory)
        action = mean
        if explore:
            noise = torch.randn(mean.shape, generator=generator, device=mean.device)
            action = mean + self.net.log_std.exp() * noise
        return Step(action.cpu(), {"obs": obs, "action": action}, memory)

    def forward(self, samples: dict[str, Tensor], memory: Tensor, episode_start: Tensor) -> Scores:
        """M sequences of L steps from their initial memory, restarting where ``episode_start``."""
        mean, value, _ = self.net.unroll(samples["obs"], memory, episode_start)
        dist = self._dist(mean)
        return Scores(dist.log_prob(samples["action"]).sum(-1, keepdim=True), value, dist.entropy().sum(-1))

    @torch.no_grad()
    def value(self, obs: Tensor, memory: Tensor) -> Tensor:
        return self.net.step(obs.to(self.net.log_std.device), memory)[1]

    def save(self, path: Path) -> None:
        """A lerobot pretrained_model directory (config, weights, identity processors): what
        ``lerobot-crowdnav-eval --policy.path=`` loads."""
        from lerobot.policies.factory import make_pre_post_processors

        self.policy.save_pretrained(path)
        pre, post = make_pre_post_processors(self.policy.config)
        pre.save_pretrained(path)
        post.save_pretrained(path)


def make_agent(sim_cfg: CrowdSimConfig, seed: int, **policy_fields) -> CrowdNavPPAgent:
    """A fresh agent on cpu, sized to the env's crowd layout, initialized from ``seed``."""
    from lerobot.configs.types import FeatureType, PolicyFeature

    cfg = CrowdNavPPConfig(
        input_features={"observation.state": PolicyFeature(FeatureType.STATE, (sim_cfg.obs_dim,))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (2,))}, device="cpu",
        num_humans=sim_cfg.num_humans, prediction_steps=sim_cfg.prediction_steps, **policy_fields)
    torch.manual_seed(seed)
    return CrowdNavPPAgent(CrowdNavPPPolicy(cfg))


def load_agent(path: Path) -> CrowdNavPPAgent:
    """The agent of a crowdnavpp pretrained_model directory, on cpu."""
    path = Path(path)
    cfg = read_policy_config(path, "crowdnavpp", "this command trains CrowdNav++ ('crowdnavpp')")
    return CrowdNavPPAgent(CrowdNavPPPolicy.from_pretrained(path, config=cfg))


def check_compatible(policy: CrowdNavPPPolicy, sim_cfg: CrowdSimConfig) -> None:
    check_observation_layout(policy.config, sim_cfg)


def build_agent(source: Path | None, sim_cfg: CrowdSimConfig, seed: int) -> CrowdNavPPAgent:
    agent = make_agent(sim_cfg, seed) if source is None else load_agent(source)
    check_compatible(agent.policy, sim_cfg)
    return agent


# The reference's run: 16 envs (its 16 processes), 10 M env steps (holonomic robot), seed 425.
register(Family("crowdnavpp", build_agent, CrowdNavPPPPOConfig, {"num_envs": 16, "env_steps": 10_000_000, "seed": 425}))
