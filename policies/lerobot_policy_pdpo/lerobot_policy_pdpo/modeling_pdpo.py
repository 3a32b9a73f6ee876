"""PDPO policy: crowd encoder -> latent z -> DDPM diffusion actor over an H-step action chunk.

Shapes (B = batch, N = humans, L = prediction steps, H = horizon, Z = latent size); all tensors
are in the processor's normalized units (state: mean/std; actions: [-1, 1]):

    observation.state (B, 9 + N*2(L+1) + N) -> CrowdEncoder -> z (B, Z)
    x_k (B, H, 2), k (B,), z -> Denoiser -> predicted noise (B, H, 2)
    z -> ValueHead -> V (B,)               (trained by fine-tuning, not by BC)

A fine-tuned policy (``ft_denoising_steps`` = K' > 0) also holds ``base``: the frozen pretrained
encoder and denoiser that run the first K - K' denoising steps.

The model knows how to encode, sample and score a chain; environments, buffers and optimizers
belong to the trainers (lerobot-train for BC, lerobot_crowdnav.finetune for diffusion PPO).
"""

from __future__ import annotations

import copy
import math
from collections import deque

import numpy as np
import torch
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_STATE
from torch import Tensor, nn

from .configuration_pdpo import PDPOConfig

ROBOT_DIM = 9  # px, py, radius, gx, gy, v_pref, theta, vx, vy


def mlp(dims: list[int], activation: type[nn.Module] = nn.ReLU, last_activation: bool = False) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(dims[:-1], dims[1:], strict=True)):
        layers.append(nn.Linear(a, b))
        if i < len(dims) - 2 or last_activation:
            layers.append(activation())
    return nn.Sequential(*layers)


class CrowdEncoder(nn.Module):
    """Human MLP, masked self-attention (residual, layer norm, dropout), robot-conditioned edge
    MLP, attention pooling over visible humans, latent MLP."""

    def __init__(self, cfg: PDPOConfig):
        super().__init__()
        self.n, self.row = cfg.num_humans, 2 * (cfg.prediction_steps + 1)
        d = cfg.human_mlp_dims[-1]
        self.human_mlp = mlp([self.row, *cfg.human_mlp_dims], last_activation=True)
        self.attention = nn.MultiheadAttention(d, cfg.attention_heads, batch_first=True)
        self.norm = nn.LayerNorm(d)
        self.dropout = nn.Dropout(cfg.dropout)
        self.edge_mlp = mlp([d + ROBOT_DIM, *cfg.edge_mlp_dims], last_activation=True)
        self.pool_mlp = mlp([cfg.edge_mlp_dims[-1], *cfg.pool_mlp_dims, 1])
        self.latent_mlp = mlp([ROBOT_DIM + cfg.edge_mlp_dims[-1], *cfg.latent_mlp_dims])

    def forward(self, state: Tensor) -> Tensor:
        b = state.shape[0]
        w = state[:, :ROBOT_DIM]  # (B, 9)
        humans = state[:, ROBOT_DIM:ROBOT_DIM + self.n * self.row].reshape(b, self.n, self.row)
        visible = state[:, -self.n:] > 0.5  # (B, N); the processor leaves the mask as 0/1
        nobody = ~visible.any(dim=1)  # (B,)
        h = self.human_mlp(humans)  # (B, N, d)
        # Keys of invisible humans are masked; a batch row with nobody visible attends to its
        # first (sentinel) row instead of producing NaN; its outputs are pooled away below.
        key_padding = ~visible
        key_padding[nobody, 0] = False
        attended, _ = self.attention(h, h, h, key_padding_mask=key_padding, need_weights=False)
        h = self.dropout(self.norm(h + attended))
        e = self.edge_mlp(torch.cat([h, w[:, None].expand(b, self.n, ROBOT_DIM)], dim=-1))  # (B, N, E)
        scores = self.pool_mlp(e).squeeze(-1).masked_fill(~visible, float("-inf"))
        scores = scores.masked_fill(nobody[:, None], 0.0)
        alpha = torch.softmax(scores, dim=1) * visible  # zero weights when nobody is visible
        pooled = (alpha[..., None] * e).sum(dim=1)  # (B, E)
        return self.latent_mlp(torch.cat([w, pooled], dim=-1))  # (B, Z)


class SinusoidalEmbedding(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim

    def forward(self, k: Tensor) -> Tensor:
        half = self.dim // 2
        freqs = torch.exp(torch.arange(half, device=k.device) * (-math.log(10000.0) / (half - 1)))
        angles = k.float()[:, None] * freqs[None]
        return torch.cat([angles.sin(), angles.cos()], dim=-1)


class Denoiser(nn.Module):
    """epsilon_theta(x_k, k, z): an MLP on [x_k flattened, z, psi(k)] (DPPO's DiffusionMLP)."""

    def __init__(self, cfg: PDPOConfig):
        super().__init__()
        t = cfg.time_embed_dim
        self.horizon = cfg.horizon
        self.time_embed = nn.Sequential(SinusoidalEmbedding(t), nn.Linear(t, 2 * t), nn.Mish(), nn.Linear(2 * t, t))
        self.net = mlp([2 * cfg.horizon + cfg.latent_dim + t, *cfg.denoiser_dims, 2 * cfg.horizon])

    def forward(self, x: Tensor, k: Tensor, z: Tensor) -> Tensor:
        out = self.net(torch.cat([x.flatten(1), z, self.time_embed(k)], dim=-1))
        return out.view(-1, self.horizon, 2)


class ValueHead(nn.Module):
    """V(z): MLP [256, 256, 256] with Mish (the critic of diffusion PPO)."""

    def __init__(self, cfg: PDPOConfig):
        super().__init__()
        self.net = mlp([cfg.latent_dim, *cfg.value_mlp_dims, 1], activation=nn.Mish)

    def forward(self, z: Tensor) -> Tensor:
        return self.net(z).squeeze(-1)


def cosine_beta_schedule(steps: int, s: float = 0.008) -> np.ndarray:
    """Nichol & Dhariwal's cosine schedule, as DPPO builds it (betas clipped at 0.999)."""
    x = np.linspace(0, steps, steps + 1)
    alphas_cumprod = np.cos(((x / steps) + s) / (1 + s) * np.pi * 0.5) ** 2
    alphas_cumprod = alphas_cumprod / alphas_cumprod[0]
    return np.clip(1 - alphas_cumprod[1:] / alphas_cumprod[:-1], 0, 0.999)


class PDPOPolicy(PreTrainedPolicy):
    """PDPO for lerobot: ``forward`` is the denoising loss, ``select_action`` samples a chunk and
    executes its first ``n_action_steps`` actions (receding horizon by default)."""

    config_class = PDPOConfig
    name = "pdpo"

    def __init__(self, config: PDPOConfig, **kwargs):
        super().__init__(config)
        config.validate_features()
        self.config = config
        self.encoder = CrowdEncoder(config)
        self.denoiser = Denoiser(config)
        self.value = ValueHead(config)
        if config.use_ema:
            self.ema = nn.ModuleDict({"encoder": copy.deepcopy(self.encoder),
                                      "denoiser": copy.deepcopy(self.denoiser)}).requires_grad_(False)
        if config.ft_denoising_steps:  # frozen pretrained nets for the first K - K' denoising steps
            self.base = nn.ModuleDict({"encoder": copy.deepcopy(self.encoder),
                                       "denoiser": copy.deepcopy(self.denoiser)}).requires_grad_(False)
        self.register_buffer("ema_updates", torch.zeros((), dtype=torch.long))
        betas = torch.tensor(cosine_beta_schedule(config.num_diffusion_steps), dtype=torch.float32)
        alphas_cumprod = torch.cumprod(1 - betas, dim=0)
        prev = torch.cat([torch.ones(1), alphas_cumprod[:-1]])
        posterior_var = betas * (1 - prev) / (1 - alphas_cumprod)
        for name, value in {
            "betas": betas,
            "alphas_cumprod": alphas_cumprod,
            "sqrt_recip_alphas_cumprod": (1 / alphas_cumprod).sqrt(),
            "sqrt_recipm1_alphas_cumprod": (1 / alphas_cumprod - 1).sqrt(),
            "posterior_std": posterior_var.clamp(min=1e-20).sqrt(),
            "posterior_mean_coef1": betas * prev.sqrt() / (1 - alphas_cumprod),
            "posterior_mean_coef2": (1 - prev) * (1 - betas).sqrt() / (1 - alphas_cumprod),
        }.items():
            self.register_buffer(name, value, persistent=False)
        self.reset()

    # -- lerobot interface -------------------------------------------------------------------
    def get_optim_params(self) -> dict:
        return [p for name, p in self.named_parameters() if name.split(".")[0] in ("encoder", "denoiser")]

    def reset(self) -> None:
        self._action_queue: deque[Tensor] = deque(maxlen=self.config.n_action_steps)

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """Denoising loss ``|eps - eps_theta(sqrt(abar_k) x_0 + sqrt(1 - abar_k) eps, z, k)|^2``
        with k uniform, averaged over the chunk steps that are not padding."""
        x0 = batch[ACTION]  # (B, H, 2) in [-1, 1]
        b = x0.shape[0]
        z = self.encoder(batch[OBS_STATE])
        k = torch.randint(0, self.config.num_diffusion_steps, (b,), device=x0.device)
        noise = torch.randn_like(x0)
        abar = self.alphas_cumprod[k][:, None, None]
        xk = abar.sqrt() * x0 + (1 - abar).sqrt() * noise
        err = (self.denoiser(xk, k, z) - noise) ** 2  # (B, H, 2)
        valid = ~batch["action_is_pad"] if "action_is_pad" in batch else torch.ones_like(err[..., 0], dtype=torch.bool)
        weights = valid[..., None].expand_as(err).float()
        loss = (err * weights).sum() / weights.sum().clamp(min=1)
        return loss, {"denoise_mse": loss.item(), "valid_fraction": valid.float().mean().item()}

    def update(self) -> None:
        """EMA of the actor's weights, called by lerobot-train after each optimizer step."""
        if not self.config.use_ema:
            return
        self.ema_updates += 1
        decay = 0.0 if self.ema_updates <= self.config.ema_start_step else self.config.ema_decay
        with torch.no_grad():
            for name in ("encoder", "denoiser"):
                for ema_p, p in zip(self.ema[name].parameters(), getattr(self, name).parameters(), strict=True):
                    ema_p.lerp_(p, 1 - decay)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """A sampled chunk ``(B, H, 2)`` for each observation (normalized units; the
        postprocessor maps them to m/s)."""
        return self.sample(batch[OBS_STATE], generator=kwargs.get("generator"))

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """The next action ``(B, 2)``: a new chunk is sampled whenever the queue of its first
        ``n_action_steps`` actions runs out (every step with the default 1)."""
        if not self._action_queue:
            chunk = self.predict_action_chunk(batch, **kwargs)
            self._action_queue.extend(chunk[:, : self.config.n_action_steps].transpose(0, 1))
        return self._action_queue.popleft()

    @torch.no_grad()
    def sample_chunks(self, batch: dict[str, Tensor], num_samples: int, generator: torch.Generator | None = None) -> Tensor:
        """``num_samples`` chunks per observation, ``(B, num_samples, H, 2)`` (multimodality)."""
        state = batch[OBS_STATE]
        chunks = self.sample(state.repeat_interleave(num_samples, dim=0), generator=generator)
        return chunks.view(state.shape[0], num_samples, self.config.horizon, 2)

    # -- diffusion -------------------------------------------------------------------------------
    def _sampling_nets(self) -> tuple[nn.Module, nn.Module]:
        if self.config.use_ema and self.ema_updates > 0:
            return self.ema["encoder"], self.ema["denoiser"]
        return self.encoder, self.denoiser

    def p_mean_std(self, denoiser: nn.Module, x: Tensor, k: Tensor, z: Tensor) -> tuple[Tensor, Tensor]:
        """Mean and std ``(B, 1, 1)`` of p(x_{k-1} | x_k) for per-sample steps ``k (B,)``: the DDPM
        posterior around the x_0 estimate, clamped to [-denoised_clip_value, +denoised_clip_value]."""
        eps = denoiser(x, k, z)
        at = lambda buf: buf[k][:, None, None]  # noqa: E731
        x0 = at(self.sqrt_recip_alphas_cumprod) * x - at(self.sqrt_recipm1_alphas_cumprod) * eps
        x0 = x0.clamp(-self.config.denoised_clip_value, self.config.denoised_clip_value)
        mean = at(self.posterior_mean_coef1) * x0 + at(self.posterior_mean_coef2) * x
        return mean, at(self.posterior_std)

    def sample(self, state: Tensor, generator: torch.Generator | None = None, exploration_std: float | None = None,
               return_chain: bool = False) -> Tensor | tuple[Tensor, Tensor]:
        """DDPM ancestral sampling of a chunk ``(B, H, 2)`` in [-1, 1] from x_K ~ N(0, I); the
        noise is clipped to +-3 (DPPO).

        ``exploration_std=None``: the posterior std floored at ``min_sampling_denoising_std`` and
        no noise at the last step (BC sampling, DPPO's deterministic evaluation). A float: the std
        floored at it and noise at every step (DPPO's fine-tuning rollouts). A fine-tuned policy
        (``ft_denoising_steps`` = K' > 0) runs steps k >= K' with the frozen ``base`` nets.
        ``return_chain``: also the fine-tuned part of the chain, ``(B, K'+1, H, 2)`` = x_{K'} ..
        x_0 (x_0 before the final clamp), which :meth:`chain_log_prob` scores."""
        cfg = self.config
        ft = cfg.ft_denoising_steps
        if return_chain and not ft:
            raise ValueError("return_chain needs a policy with ft_denoising_steps > 0")
        encoder, denoiser = self._sampling_nets()
        z = encoder(state)
        z_base = self.base["encoder"](state) if 0 < ft < cfg.num_diffusion_steps else z
        b = state.shape[0]
        shape = (b, cfg.horizon, 2)
        floor = cfg.min_sampling_denoising_std if exploration_std is None else exploration_std
        x = torch.randn(shape, device=state.device, generator=generator)
        chain = []
        for k in reversed(range(cfg.num_diffusion_steps)):
            if return_chain and k == ft - 1:
                chain.append(x)
            frozen = 0 < ft <= k
            kk = torch.full((b,), k, device=state.device, dtype=torch.long)
            mean, std = self.p_mean_std(self.base["denoiser"] if frozen else denoiser, x, kk, z_base if frozen else z)
            if k == 0 and exploration_std is None:
                x = mean
            else:
                noise = torch.randn(shape, device=state.device, generator=generator).clamp(-3, 3)
                x = mean + std.clamp(min=floor) * noise
            if return_chain and k < ft:
                chain.append(x)
        chunk = x.clamp(-1, 1)
        return (chunk, torch.stack(chain, dim=1)) if return_chain else chunk

    def chain_log_prob(self, state: Tensor, chain: Tensor, min_std: float) -> tuple[Tensor, Tensor]:
        """Log-probabilities ``(B, K')`` of the fine-tuned transitions of stored chains
        ``(B, K'+1, H, 2)`` under the trained encoder and denoiser, and the latent ``z (B, Z)``.

        Each transition x_k -> x_{k-1} is Gaussian with the network's mean and the posterior std
        floored at ``min_std``; the per-element log-density is clamped to [-5, 2] and averaged
        over the chunk (DPPO). Index i = 0 is the noisiest fine-tuned step (k = K'-1), i = K'-1
        the final one (k = 0). All K' steps run as one batched denoiser call."""
        ft = self.config.ft_denoising_steps
        b = state.shape[0]
        if chain.shape[1:] != (ft + 1, self.config.horizon, 2):
            raise ValueError(f"chain has shape {tuple(chain.shape)}, expected (B, {ft + 1}, {self.config.horizon}, 2)")
        z = self.encoder(state)
        k = torch.arange(ft - 1, -1, -1, device=state.device).repeat(b)  # (B*K',)
        x_k = chain[:, :-1].reshape(b * ft, self.config.horizon, 2)
        x_prev = chain[:, 1:].reshape(b * ft, self.config.horizon, 2)
        mean, std = self.p_mean_std(self.denoiser, x_k, k, z.repeat_interleave(ft, dim=0))
        dist = torch.distributions.Normal(mean, std.clamp(min=min_std))
        logp = dist.log_prob(x_prev).clamp(-5, 2).mean(dim=(-2, -1))
        return logp.view(b, ft), z

    def parameter_counts(self) -> dict[str, int]:
        """Actor = encoder + denoiser (paper: 0.848 M); critic = value head (paper: 0.201 M)."""
        count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
        return {"actor": count(self.encoder) + count(self.denoiser), "critic": count(self.value)}
