"""PDPO as an actor-critic for the PPO loop (DPPO's ``agent/`` side of the model/agent split):
the critic, the chain scoring, and reading/writing fine-tuning checkpoints.

A decision is one sampled action chunk, of which the env executes the first action (receding
horizon); it is stored as its state and chain and scored as its K' fine-tuned denoising
transitions:

    stored["state"]  (B, 269)            normalized observation.state (the policy's preprocessor)
    stored["chain"]  (B, K'+1, H, 2)     x_{K'} .. x_0 of the sampled chunk, normalized action units
    stored["latent"] (B, Z)              the encoder's latent (only with ``freeze_encoder``)
    Scores.logp      (L, M, K')          log-probabilities of the K' transitions
    Scores.value     (L, M)              V(z), z the trained encoder's latent through a stop-gradient

Fine-tuning checkpoints are lerobot ``pretrained_model`` directories of the fine-tuned policy
(``ft_denoising_steps`` = K', frozen ``base`` included) with the critic beside it in
``critic.safetensors`` (lerobot ignores the file). Checkpoints written before the actor/critic
split hold the critic as ``value.*`` in ``model.safetensors``; it is read from there.
"""

from __future__ import annotations

import copy
from pathlib import Path

import torch
from lerobot_policy_pdpo.modeling_pdpo import DiffusionActor, PDPOPolicy, mlp
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

from ..checkpoint_files import CRITIC, WEIGHTS
from ..layout import obs_dim
from ..measure.episodes import on_device
from ..sim.config import CrowdSimConfig
from .agent import Scores, Step, check_observation_layout, read_policy_config
from .config import DiffusionPPOConfig

OBS = "observation.state"


class ValueHead(nn.Module):
    """V(s): MLP ``value_mlp_dims`` ([256, 256, 256] in the paper) with Mish, reading
    ``inputs`` (``DiffusionPPOConfig.critic_input``): the encoder's latent z (the paper), the
    normalized observation (DPPO's critic for state inputs) or both, concatenated."""

    def __init__(self, latent_dim: int, dims: tuple[int, ...], inputs: str = "latent", state_dim: int = 0):
        super().__init__()
        self.inputs = inputs
        width = {"latent": latent_dim, "state": state_dim, "latent+state": latent_dim + state_dim}[inputs]
        self.net = mlp([width, *dims, 1], activation=nn.Mish)

    def forward(self, z: Tensor, state: Tensor) -> Tensor:
        """``z (B, Z)`` (no gradient reaches the encoder through it), ``state (B, D)``."""
        x = {"latent": lambda: z.detach(), "state": lambda: state,
             "latent+state": lambda: torch.cat([z.detach(), state], dim=-1)}[self.inputs]()
        return self.net(x).squeeze(-1)


def make_critic(pcfg, cfg: DiffusionPPOConfig) -> ValueHead:
    """A fresh critic of policy config ``pcfg`` reading ``cfg.critic_input``."""
    return ValueHead(pcfg.latent_dim, pcfg.value_mlp_dims, cfg.critic_input,
                     obs_dim(pcfg.num_humans, pcfg.prediction_steps))


def transition_log_prob(actor: DiffusionActor, z: Tensor, chain: Tensor, min_std: float,
                        actions: int | None = None) -> Tensor:
    """Log-probabilities ``(B, K')`` of the transitions of chains ``(B, K'+1, H, 2)`` that ran the
    last K' reverse steps, under ``actor`` given the latent ``z (B, Z)``.

    Each transition x_k -> x_{k-1} is Gaussian with the network's mean and the posterior std
    floored at ``min_std``; the per-element log-density is clamped to [-5, 2] and averaged over
    the chunk's first ``actions`` actions (all H when None; DPPO's code keeps the executed ones).
    Index i = 0 is the noisiest step (k = K'-1), i = K'-1 the final one (k = 0). All K' steps run
    as one batched denoiser call."""
    b, ft = chain.shape[0], chain.shape[1] - 1
    k = torch.arange(ft - 1, -1, -1, device=chain.device).repeat(b)  # (B*K',)
    x_k = chain[:, :-1].reshape(b * ft, *chain.shape[2:])
    x_prev = chain[:, 1:].reshape(b * ft, *chain.shape[2:])
    mean, std = actor.p_mean_std(x_k, k, z)  # one latent per chain, shared by its K' transitions
    dens = torch.distributions.Normal(mean, std.clamp(min=min_std)).log_prob(x_prev).clamp(-5, 2)
    logp = dens[:, :actions].mean(dim=(-2, -1))
    return logp.view(b, ft)


class DiffusionPPOAgent(nn.Module):
    """The actor-critic protocol (rl/agent.py) for a fine-tuning PDPO policy. Feed-forward."""

    recurrent = False

    def __init__(self, policy: PDPOPolicy, critic: ValueHead, pre, post, cfg: DiffusionPPOConfig):
        super().__init__()
        self.policy, self.critic = policy, critic
        self.pre, self.post, self.cfg = pre, post, cfg
        self.n_parts = policy.config.ft_denoising_steps  # K' transitions per decision
        if cfg.freeze_encoder:
            base = policy.base.encoder.state_dict() if policy.base is not None else {}
            if any(not torch.equal(v, base[k]) for k, v in policy.actor.encoder.state_dict().items() if k in base):
                raise ValueError("--ppo.freeze_encoder=true: this policy's encoder was fine-tuned (it differs from "
                                 "its frozen base's); continue it with --ppo.freeze_encoder=false")
            policy.actor.encoder.requires_grad_(False)

    def initial_memory(self, num_envs: int) -> None:
        return None

    def param_groups(self) -> dict[str, list[nn.Parameter]]:
        actor = [p for p in self.policy.actor.parameters() if p.requires_grad]
        return {"actor": actor, "critic": list(self.critic.parameters())}

    def _normalize(self, obs: Tensor) -> Tensor:
        return self.pre({OBS: obs})[OBS].to(self.critic.net[0].weight.device)

    @torch.no_grad()
    def act(self, obs: Tensor, memory: None, explore: bool, generator: torch.Generator) -> Step:
        """Exploring: noise at every denoising step, floored at ``min_sampling_denoising_std``;
        otherwise DPPO's deterministic sampling. The action is the chunk's first, in m/s."""
        state = self._normalize(obs)
        # A frozen encoder is the base's too: one encoding serves the whole chain and every update.
        latent = self.policy.actor.encoder(state) if self.cfg.freeze_encoder else None
        chain = self.policy.sample_chain(state, generator, self.cfg.min_sampling_denoising_std if explore else None,
                                         latent)
        action = self.post(chain[:, -1, 0].clamp(-1, 1)).cpu()  # (B, 2)
        stored = {"state": state, "chain": chain}
        if latent is not None:
            stored["latent"] = latent
        return Step(action, stored, None)

    def forward(self, samples: dict[str, Tensor], memory: None, episode_start: Tensor) -> Scores:
        L, M = samples["state"].shape[:2]
        chain = samples["chain"].flatten(0, 1)
        z = samples["latent"].flatten(0, 1) if "latent" in samples else self.policy.actor.encoder(samples["state"].flatten(0, 1))
        actions = 1 if self.cfg.logprob_actions == "executed" else None  # receding horizon: one executed
        logp = transition_log_prob(self.policy.actor, z, chain, self.cfg.min_logprob_denoising_std, actions)
        # The critic reads the shared encoder's latent through a stop-gradient, so a fresh critic
        # cannot overwrite the pretrained features.
        return Scores(logp.view(L, M, -1), self.critic(z, samples["state"].flatten(0, 1)).view(L, M), None)

    @torch.no_grad()
    def value(self, obs: Tensor, memory: None) -> Tensor:
        state = self._normalize(obs)
        return self.critic(self.policy.actor.encoder(state), state)

    def save(self, path: Path) -> None:
        """A lerobot pretrained_model directory plus ``critic.safetensors``."""
        self.policy.save_pretrained(path)
        self.pre.save_pretrained(path)
        self.post.save_pretrained(path)
        save_file({k: v.contiguous() for k, v in self.critic.state_dict().items()}, str(Path(path) / CRITIC))


def load_agent(path: Path, cfg: DiffusionPPOConfig, seed: int) -> DiffusionPPOAgent:
    """The agent to fine-tune, on cpu. A BC checkpoint becomes a fine-tuning policy whose trained
    and frozen actors both start from its sampling (EMA) weights, with a fresh critic; a
    fine-tuned checkpoint is taken as it is, critic included."""
    from lerobot.policies.factory import make_pre_post_processors

    path = Path(path)
    pcfg = read_policy_config(path, "pdpo", "diffusion PPO fine-tunes PDPO ('pdpo')")
    ft = cfg.ft_denoising_steps
    if pcfg.ft_denoising_steps and (pcfg.ft_denoising_steps, pcfg.ddim_steps) != (ft, cfg.ddim_steps):
        raise ValueError(f"{path} was fine-tuned with ft_denoising_steps={pcfg.ft_denoising_steps}, ddim_steps="
                         f"{pcfg.ddim_steps}, not {ft}, {cfg.ddim_steps}")
    if cfg.ddim_steps and pcfg.num_diffusion_steps % cfg.ddim_steps:
        raise ValueError(f"--ppo.ddim_steps={cfg.ddim_steps} must divide the policy's {pcfg.num_diffusion_steps} steps")
    if ft > (cfg.ddim_steps or pcfg.num_diffusion_steps):
        raise ValueError(f"--ppo.ft_denoising_steps={ft} exceeds the {cfg.ddim_steps or pcfg.num_diffusion_steps} "
                         "sampling steps")
    loaded = PDPOPolicy.from_pretrained(path, config=pcfg)
    if pcfg.ft_denoising_steps:
        policy = loaded
        critic = make_critic(pcfg, cfg)
        saved = _saved_critic(path)
        if saved["net.0.weight"].shape != critic.net[0].weight.shape:
            raise ValueError(f"{path}'s critic does not read --ppo.critic_input={cfg.critic_input} (its first layer takes "
                             f"{saved['net.0.weight'].shape[1]} inputs): pass the critic_input it was fine-tuned with")
        critic.load_state_dict(saved)
    else:
        ft_cfg = copy.deepcopy(pcfg)
        ft_cfg.use_ema, ft_cfg.ft_denoising_steps, ft_cfg.ddim_steps = False, ft, cfg.ddim_steps
        policy = PDPOPolicy(ft_cfg)
        weights = loaded.sampling_actor().state_dict()
        policy.actor.load_state_dict(weights)
        policy.base.load_state_dict(weights)
        torch.manual_seed(seed)  # the fresh critic
        critic = make_critic(pcfg, cfg)
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(path), **on_device("cpu"))
    return DiffusionPPOAgent(policy, critic, pre, post, cfg)


def _saved_critic(path: Path) -> dict[str, Tensor]:
    if (path / CRITIC).exists():
        return load_file(str(path / CRITIC))
    legacy = load_file(str(path / WEIGHTS))  # written before the actor/critic split
    critic = {k.removeprefix("value."): v for k, v in legacy.items() if k.startswith("value.")}
    if not critic:
        raise FileNotFoundError(f"{path} is a fine-tuned PDPO policy without its critic ({CRITIC}): continue "
                                "fine-tuning from the checkpoint the fine-tuning wrote, critic included")
    return critic


def check_compatible(policy: PDPOPolicy, sim_cfg: CrowdSimConfig) -> None:
    check_observation_layout(policy.config, sim_cfg)
    if policy.config.n_action_steps != 1:
        raise ValueError("diffusion PPO executes the first action of each chunk (receding horizon): "
                         f"the policy has n_action_steps={policy.config.n_action_steps}")
