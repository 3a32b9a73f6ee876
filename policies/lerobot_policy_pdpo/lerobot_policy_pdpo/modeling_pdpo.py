"""PDPO policy: crowd encoder -> latent z -> DDPM diffusion actor over an H-step action chunk.

Shapes (B = batch, N = humans, L = prediction steps, H = horizon, Z = latent size); all tensors
are in the processor's normalized units (state: mean/std; actions: [-1, 1]):

    observation.state (B, 9 + N*2(L+1) + N) -> CrowdEncoder -> z (B, Z)
    x_k (B, H, 2), k (B,), z -> Denoiser -> predicted noise (B, H, 2)

``DiffusionActor`` is the model (encoder + denoiser + the reverse process: encode, sample, score
a chain); ``PDPOPolicy`` is the thin lerobot wrapper around it (EMA, the frozen ``base`` of a
fine-tuned policy, ``select_action``). There is no critic here: diffusion PPO keeps its value
head on the RL side (``lerobot_crowdnav.rl.dppo``); environments, buffers and optimizers belong
to the trainers (lerobot-train for BC, lerobot-crowdnav-finetune for diffusion PPO).
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

from lerobot_crowdnav.data.fast_loader import install as install_fast_loader
from lerobot_crowdnav.layout import ROBOT_DIM, SELF_DIM, human_row_dim, humans_slice, mask_slice, visible_prefix_groups

from .configuration_pdpo import PDPOConfig

# Groups of similar visible counts in which training runs the encoder's per-human part (speed only).
HUMAN_GROUPS = 8


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
        self.n, self.row = cfg.num_humans, human_row_dim(cfg.prediction_steps)
        self.humans, self.mask = humans_slice(cfg.num_humans, cfg.prediction_steps), mask_slice(cfg.num_humans, cfg.prediction_steps)
        self.velocity_dropout = cfg.velocity_dropout
        d = cfg.human_mlp_dims[-1]
        self.human_mlp = mlp([self.row, *cfg.human_mlp_dims], last_activation=True)
        self.attention = nn.MultiheadAttention(d, cfg.attention_heads, batch_first=True)
        self.norm = nn.LayerNorm(d)
        self.dropout = nn.Dropout(cfg.dropout)
        self.edge_mlp = mlp([d + SELF_DIM, *cfg.edge_mlp_dims], last_activation=True)
        self.pool_mlp = mlp([cfg.edge_mlp_dims[-1], *cfg.pool_mlp_dims, 1])
        self.latent_mlp = mlp([SELF_DIM + cfg.edge_mlp_dims[-1], *cfg.latent_mlp_dims])

    def forward(self, state: Tensor) -> Tensor:
        b = state.shape[0]
        w = self._robot_input(state[:, :SELF_DIM])  # (B, 9)
        humans = state[:, self.humans].reshape(b, self.n, self.row)
        mask = state[:, self.mask]
        if torch.any(torch.minimum(mask.abs(), (mask - 1).abs()) > 1e-4):
            raise ValueError(
                "observation.state's visibility mask is not 0/1 after the preprocessor: its statistics are "
                "not PDPO's (visible-only human moments, identity mask: processor_pdpo.crowd_state_stats). "
                "lerobot-train --policy.path=<PDPO checkpoint> with a --dataset replaces them with the "
                "dataset's raw statistics; continue a run with --resume=true instead, or train from "
                "--policy.type=pdpo.")
        visible = mask > 0.5  # (B, N)
        if torch.is_grad_enabled() and not (visible[:, 1:] & ~visible[:, :-1]).any():
            # Training (lerobot-train, the PPO update): only the visible prefix of each row, in
            # groups of similar counts; the same values at a fraction of the per-human work.
            groups, back = visible_prefix_groups(visible.sum(dim=1), HUMAN_GROUPS)
            pooled = torch.cat([self._pool(humans[rows, :k], visible[rows, :k], w[rows]) for rows, k in groups])[back]
        else:  # acting: every slot, as the shipped policies were evaluated (bitwise)
            pooled = self._pool(humans, visible, w)
        return self.latent_mlp(torch.cat([w, pooled], dim=-1))  # (B, Z)

    def _pool(self, humans: Tensor, visible: Tensor, w: Tensor) -> Tensor:
        """Human rows ``(B, n, row)``, their visibility ``(B, n)``, the robot ``(B, 9)`` -> the
        attention-pooled edge features ``(B, E)``; rows past the visible ones change nothing."""
        b, n = visible.shape
        nobody = ~visible.any(dim=1)  # (B,)
        h = self.human_mlp(humans)  # (B, n, d)
        # Keys of invisible humans are masked; a batch row with nobody visible attends to its
        # first (sentinel) row instead of producing NaN; its outputs are pooled away below.
        key_padding = ~visible
        key_padding[nobody, 0] = False
        attended, _ = self.attention(h, h, h, key_padding_mask=key_padding, need_weights=False)
        h = self.dropout(self.norm(h + attended))
        e = self.edge_mlp(torch.cat([h, w[:, None].expand(b, n, SELF_DIM)], dim=-1))  # (B, n, E)
        scores = self.pool_mlp(e).squeeze(-1).masked_fill(~visible, float("-inf"))
        scores = scores.masked_fill(nobody[:, None], 0.0)
        alpha = torch.softmax(scores, dim=1) * visible  # zero weights when nobody is visible
        return (alpha[..., None] * e).sum(dim=1)

    def _robot_input(self, w: Tensor) -> Tensor:
        """The robot's 9 floats with the velocity zeroed (its normalized mean) per
        ``velocity_dropout``: always at 1.0, per sample in training mode otherwise."""
        p = self.velocity_dropout
        if p == 0 or (p < 1 and not self.training):
            return w
        keep = torch.ones_like(w)
        if p == 1:
            keep[:, ROBOT_DIM:] = 0
        else:
            keep[:, ROBOT_DIM:] = (torch.rand(w.shape[0], 1, device=w.device) >= p).to(w.dtype)
        return w * keep


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
        """``x (B, H, 2)``, ``k (B,)``, ``z (B, Z)``, or ``(B / r, Z)``: one latent for each r
        consecutive rows (a state's noise draws or chain transitions), whose share of the first
        layer (256 of its 282 inputs) is then computed once per latent instead of r times."""
        if z.shape[0] == x.shape[0]:
            out = self.net(torch.cat([x.flatten(1), z, self.time_embed(k)], dim=-1))
            return out.view(-1, self.horizon, 2)
        if x.shape[0] % z.shape[0]:
            raise ValueError(f"{x.shape[0]} rows of x cannot share {z.shape[0]} latents evenly")
        first = self.net[0]
        w_x, w_z, w_k = first.weight.split([x[0].numel(), z.shape[1], first.in_features - x[0].numel() - z.shape[1]], dim=1)
        shared = nn.functional.linear(z, w_z, first.bias).repeat_interleave(x.shape[0] // z.shape[0], dim=0)
        h = shared + nn.functional.linear(x.flatten(1), w_x) + nn.functional.linear(self.time_embed(k), w_k)
        return self.net[1:](h).view(-1, self.horizon, 2)


def cosine_beta_schedule(steps: int, s: float = 0.008) -> np.ndarray:
    """Nichol & Dhariwal's cosine schedule, as DPPO builds it (betas clipped at 0.999)."""
    x = np.linspace(0, steps, steps + 1)
    alphas_cumprod = np.cos(((x / steps) + s) / (1 + s) * np.pi * 0.5) ** 2
    alphas_cumprod = alphas_cumprod / alphas_cumprod[0]
    return np.clip(1 - alphas_cumprod[1:] / alphas_cumprod[:-1], 0, 0.999)


class DiffusionActor(nn.Module):
    """The model: crowd encoder, denoiser and the reverse process over an action chunk (DPPO's
    ``model/``: it knows how to encode, sample and give the per-step Gaussian of a chain).

    Reverse steps are indexed k = S-1 (noisiest) .. 0 over the sampler's S steps: DDPM runs all
    K (k is the timestep), DDIM runs S = ``ddim_steps`` of them at timesteps k * K/S."""

    def __init__(self, cfg: PDPOConfig):
        super().__init__()
        self.horizon, self.clip_value = cfg.horizon, cfg.denoised_clip_value
        self.ddim = cfg.ddim_steps > 0
        self.encoder = CrowdEncoder(cfg)
        self.denoiser = Denoiser(cfg)
        betas = torch.tensor(cosine_beta_schedule(cfg.num_diffusion_steps), dtype=torch.float32)
        alphas_cumprod = torch.cumprod(1 - betas, dim=0)
        self.register_buffer("alphas_cumprod", alphas_cumprod, persistent=False)  # training: all K
        t = torch.arange(cfg.sampling_steps) * (cfg.num_diffusion_steps // cfg.sampling_steps)
        abar = alphas_cumprod[t]
        prev = torch.cat([torch.ones(1), abar[:-1]])  # abar of the next reverse step's timestep
        buffers = {"timestep": t, "sqrt_recip_abar": (1 / abar).sqrt(), "sqrt_recipm1_abar": (1 / abar - 1).sqrt()}
        if self.ddim:  # DDIM (Song et al.), eta = 1 while exploring, 0 otherwise
            sigma = ((1 - prev) / (1 - abar) * (1 - abar / prev)).sqrt()
            buffers |= {"sqrt_abar": abar.sqrt(), "sqrt_one_minus_abar": (1 - abar).sqrt(), "sqrt_prev": prev.sqrt(),
                        "ddim_sigma": sigma, "dir_coef": (1 - prev - sigma ** 2).clamp(min=0).sqrt(),
                        "dir_coef_deterministic": (1 - prev).sqrt()}
        else:  # the DDPM posterior q(x_{k-1} | x_k, x_0)
            betas = betas[t]
            buffers |= {"posterior_std": (betas * (1 - prev) / (1 - abar)).clamp(min=1e-20).sqrt(),
                        "posterior_mean_coef1": betas * prev.sqrt() / (1 - abar),
                        "posterior_mean_coef2": (1 - prev) * (1 - betas).sqrt() / (1 - abar)}
        for name, value in buffers.items():
            self.register_buffer(name, value, persistent=False)

    def denoising_loss(self, state: Tensor, x0: Tensor, valid: Tensor, noise_draws: int = 1) -> Tensor:
        """``|eps - eps_theta(sqrt(abar_k) x_0 + sqrt(1 - abar_k) eps, z, k)|^2`` with k uniform,
        averaged over the chunk steps ``valid (B, H)`` (not padding); ``x0 (B, H, 2)`` in [-1, 1].
        ``noise_draws`` (k, eps) pairs per observation share one encoding: the encoder costs far
        more than the denoiser, so extra draws lower the gradient's variance almost for free."""
        z = self.encoder(state)  # one latent per observation, shared by its draws (Denoiser.forward)
        if noise_draws > 1:
            x0, valid = (t.repeat_interleave(noise_draws, dim=0) for t in (x0, valid))
        b = x0.shape[0]
        k = torch.randint(0, len(self.alphas_cumprod), (b,), device=x0.device)
        noise = torch.randn_like(x0)
        abar = self.alphas_cumprod[k][:, None, None]
        xk = abar.sqrt() * x0 + (1 - abar).sqrt() * noise
        err = (self.denoiser(xk, k, z) - noise) ** 2  # (B, H, 2)
        weights = valid[..., None].expand_as(err).float()
        return (err * weights).sum() / weights.sum().clamp(min=1)

    def p_mean_std(self, x: Tensor, k: Tensor, z: Tensor, deterministic: bool = False) -> tuple[Tensor, Tensor]:
        """Mean and std ``(B, 1, 1)`` of p(x_{k-1} | x_k) for per-sample reverse steps ``k (B,)``
        around the x_0 estimate clamped to [-denoised_clip_value, +denoised_clip_value]: the DDPM
        posterior, or DDIM with eta = 1 (``deterministic``: eta = 0, std 0), whose direction term
        uses the noise implied by the clamped x_0 (DPPO). ``z``: per row, or per r consecutive rows
        (``Denoiser.forward``)."""
        eps = self.denoiser(x, self.timestep[k], z)
        at = lambda buf: buf[k][:, None, None]  # noqa: E731
        x0 = at(self.sqrt_recip_abar) * x - at(self.sqrt_recipm1_abar) * eps
        x0 = x0.clamp(-self.clip_value, self.clip_value)
        if not self.ddim:
            return at(self.posterior_mean_coef1) * x0 + at(self.posterior_mean_coef2) * x, at(self.posterior_std)
        eps = (x - at(self.sqrt_abar) * x0) / at(self.sqrt_one_minus_abar)
        if deterministic:
            return at(self.sqrt_prev) * x0 + at(self.dir_coef_deterministic) * eps, torch.zeros_like(at(self.ddim_sigma))
        return at(self.sqrt_prev) * x0 + at(self.dir_coef) * eps, at(self.ddim_sigma)

    def denoise(self, state: Tensor, x: Tensor, steps: range, std_floor: float, final_noise: bool,
                generator: torch.Generator | None = None, latent: Tensor | None = None) -> Tensor:
        """Run the reverse steps ``k in steps`` (descending) from ``x (B, H, 2)``; returns the chain
        ``(B, len(steps)+1, H, 2)``, ``x`` first. ``final_noise`` (fine-tuning rollouts): every
        step adds its std floored at ``std_floor`` times noise clipped to +-3 (DPPO). Otherwise
        DDPM adds it at every step but k = 0 and DDIM samples deterministically (eta = 0).
        ``latent``: the state's encoding when the caller already has it."""
        z = self.encoder(state) if latent is None else latent
        chain = [x]
        for k in steps:
            kk = torch.full((x.shape[0],), k, device=x.device, dtype=torch.long)
            if self.ddim and not final_noise:
                x = self.p_mean_std(x, kk, z, deterministic=True)[0]
                chain.append(x)
                continue
            mean, std = self.p_mean_std(x, kk, z)
            if k == 0 and not final_noise:
                x = mean
            else:
                x = mean + std.clamp(min=std_floor) * torch.randn(x.shape, device=x.device, generator=generator).clamp(-3, 3)
            chain.append(x)
        return torch.stack(chain, dim=1)


class PDPOPolicy(PreTrainedPolicy):
    """PDPO for lerobot: ``forward`` is the denoising loss, ``select_action`` samples a chunk and
    executes its first ``n_action_steps`` actions (receding horizon by default).

    Holds ``actor`` (trained), ``ema`` (its average, used for sampling when ``use_ema``) and, for a
    fine-tuned policy (``ft_denoising_steps`` = K' > 0), ``base``: the frozen pretrained actor
    that runs the first K - K' denoising steps."""

    config_class = PDPOConfig
    name = "pdpo"

    def __init__(self, config: PDPOConfig, **kwargs):
        super().__init__(config)
        config.validate_features()
        self.config = config
        self.actor = DiffusionActor(config)
        self.ema = copy.deepcopy(self.actor).requires_grad_(False) if config.use_ema else None
        self.base = copy.deepcopy(self.actor).requires_grad_(False) if config.ft_denoising_steps else None
        self.register_buffer("ema_updates", torch.zeros((), dtype=torch.long))
        self.register_load_state_dict_pre_hook(_read_legacy_keys)
        self.reset()

    @classmethod
    def _load_as_safetensor(cls, model, model_file: str, map_location: str, strict: bool):
        """Always strict (lerobot's default is not): missing weights must not load as random ones."""
        return super()._load_as_safetensor(model, model_file, map_location, True)

    # -- lerobot interface -------------------------------------------------------------------
    def get_optim_params(self) -> list[nn.Parameter]:
        """The actor's parameters, for lerobot-train. Training PDPO is where our datasets are read,
        so this also turns on their fast reads (lerobot_crowdnav.data.fast_loader)."""
        install_fast_loader()
        return list(self.actor.parameters())

    def reset(self) -> None:
        self._action_queue: deque[Tensor] = deque(maxlen=self.config.n_action_steps)

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """The denoising loss over the chunk steps that are not padding."""
        x0 = batch[ACTION]  # (B, H, 2) in [-1, 1]
        valid = ~batch["action_is_pad"] if "action_is_pad" in batch else torch.ones_like(x0[..., 0], dtype=torch.bool)
        loss = self.actor.denoising_loss(batch[OBS_STATE], x0, valid, self.config.noise_draws)
        return loss, {"denoise_mse": loss.item(), "valid_fraction": valid.float().mean().item()}

    def update(self) -> None:
        """EMA of the actor's weights, called by lerobot-train after each optimizer step."""
        if self.ema is None:
            return
        self.ema_updates += 1
        decay = 0.0 if self.ema_updates <= self.config.ema_start_step else self.config.ema_decay
        with torch.no_grad():
            for ema_p, p in zip(self.ema.parameters(), self.actor.parameters(), strict=True):
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

    # -- sampling --------------------------------------------------------------------------------
    def sampling_actor(self) -> DiffusionActor:
        """The EMA weights once they exist and ``use_ema`` is on, else the trained ones."""
        if self.config.use_ema and self.ema is not None and self.ema_updates > 0:
            return self.ema
        return self.actor

    def sample(self, state: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """A chunk ``(B, H, 2)`` in [-1, 1]: the end of :meth:`sample_chain`, clamped."""
        return self.sample_chain(state, generator)[:, -1].clamp(-1, 1)

    def sample_chain(self, state: Tensor, generator: torch.Generator | None = None,
                     exploration_std: float | None = None, latent: Tensor | None = None) -> Tensor:
        """Reverse process (DDPM, or DDIM with ``ddim_steps``) from pure noise; returns the
        trained part of the chain, ``(B, K'+1, H, 2)`` = x_{K'} .. x_0 (K' = all sampling steps for
        a BC policy; x_0 before the final clamp). A fine-tuned policy runs steps k >= K' with the
        frozen ``base``.

        ``exploration_std=None``: std floored at ``min_sampling_denoising_std``, no noise at the
        last step (BC sampling, DPPO's deterministic evaluation). A float: std floored at it and
        noise at every step (DPPO's fine-tuning rollouts). ``latent``: the state's encoding, for
        both the frozen and the trained steps (fine-tuning with a frozen encoder computes it once)."""
        cfg = self.config
        floor = cfg.min_sampling_denoising_std if exploration_std is None else exploration_std
        explore = exploration_std is not None
        x = torch.randn((state.shape[0], cfg.horizon, 2), device=state.device, generator=generator)
        trained = cfg.ft_denoising_steps or cfg.sampling_steps
        if trained < cfg.sampling_steps:
            frozen_steps = range(cfg.sampling_steps - 1, trained - 1, -1)
            x = self.base.denoise(state, x, frozen_steps, floor, explore, generator, latent)[:, -1]
        return self.sampling_actor().denoise(state, x, range(trained - 1, -1, -1), floor, explore, generator, latent)

    def parameter_counts(self) -> dict[str, int]:
        """Actor = encoder + denoiser (paper: 0.848 M); the critic lives with diffusion PPO."""
        return {"actor": sum(p.numel() for p in self.actor.parameters())}


def _read_legacy_keys(module: nn.Module, state_dict: dict, prefix: str, *args) -> None:
    """Checkpoints written before the actor/critic split hold the actor at ``encoder.*`` /
    ``denoiser.*`` and a value head at ``value.*``: the actor is renamed, the value head left to
    diffusion PPO (lerobot_crowdnav.rl.dppo reads it from the file)."""
    for key in list(state_dict):
        rest = key[len(prefix):]
        if rest.startswith(("encoder.", "denoiser.")):
            state_dict[f"{prefix}actor.{rest}"] = state_dict.pop(key)
        elif rest.startswith("value."):
            del state_dict[key]
