"""PDPO configuration. Numbers from the PDPO paper / DPPO are marked with their source."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import NormalizationMode
from lerobot.optim.optimizers import AdamWConfig, OptimizerConfig

from lerobot_crowdnav.layout import SENTINEL, check_policy_features, obs_dim


@OptimizerConfig.register_subclass("pdpo_adamw")
@dataclass
class FusedAdamWConfig(AdamWConfig):
    """lerobot's AdamW with torch's fused kernel: one pass over the parameters instead of a loop
    over its 34 tensors, 5.7x faster per step on one CPU core (1.75 against 9.96 ms), which was
    12 % of a BC step. A resumed run keeps the kernel it was saved with (torch restores it)."""

    fused: bool = True


@PreTrainedConfig.register_subclass("pdpo")
@dataclass
class PDPOConfig(PreTrainedConfig):
    """PDPO: a crowd encoder and a DDPM diffusion actor over a short action chunk.

    The input is ``observation.state``, the 269-float crowd observation of lerobot-crowdnav
    (``[robot 7 | velocity 2 | humans N x 2(L+1) | mask N]``); the output is a chunk of ``horizon``
    world-frame velocities, normalized to [-1, 1] by the processor (the x_0 clamp assumes it).
    """

    # -- inputs / outputs --------------------------------------------------------------------
    n_obs_steps: int = 1
    # Action chunk length H (paper: 5; H = 1 is the "w/o action chunk" ablation).
    horizon: int = 5
    # Actions executed per sampled chunk: 1 = receding horizon (replan every step, the paper).
    n_action_steps: int = 1
    # Crowd layout of observation.state: humans and constant-velocity prediction steps L.
    num_humans: int = 20
    prediction_steps: int = 5
    # Value that fills the rows of invisible humans in observation.state (lerobot-crowdnav: 15).
    sentinel_value: float = SENTINEL
    # MEAN_STD for the state (human-row statistics recomputed without the sentinel rows, see
    # processor_pdpo), MIN_MAX for actions: [-1, 1].
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {"STATE": NormalizationMode.MEAN_STD, "ACTION": NormalizationMode.MIN_MAX})

    # -- crowd encoder -------------------------------------------------------------------------
    # MLP_human on each 2(L+1)-float human row.
    human_mlp_dims: tuple[int, ...] = (128, 128)
    # Masked multi-head self-attention over visible humans (embedding = human_mlp_dims[-1]).
    attention_heads: int = 4
    dropout: float = 0.1
    # MLP_edge on [attended human, robot state w].
    edge_mlp_dims: tuple[int, ...] = (256, 256)
    # MLP_att scores for attention pooling over visible humans.
    pool_mlp_dims: tuple[int, ...] = (128,)
    # MLP_latent on [w, pooled edges] -> z (last entry = latent size).
    latent_mlp_dims: tuple[int, ...] = (512, 256)
    # Robot-velocity dropout against the copycat shortcut: the velocity entries (7-8) are the
    # previous executed action, and cloning from them copies it instead of reacting to the crowd.
    # Each training sample has them replaced by 0 (the dataset's mean velocity, after
    # normalization) with this probability; at 1.0 the encoder never reads them, in training and
    # acting alike. 0: the paper's encoder (docs/recipes.md measures the settings).
    velocity_dropout: float = 0.0

    # -- diffusion actor (DPPO DiffusionMLP) ---------------------------------------------------
    # Denoiser MLP on [x_k flattened, z, psi(k)], ReLU (paper: [512, 256, 256]).
    denoiser_dims: tuple[int, ...] = (512, 256, 256)
    # Sinusoidal timestep embedding size (paper: 16), followed by an MLP (16 -> 32 -> 16, Mish).
    time_embed_dim: int = 16
    # Denoising steps K (paper: 20), cosine beta schedule, epsilon prediction, DDPM sampling.
    num_diffusion_steps: int = 20
    # Sampling: 0 = DDPM over all K steps (the paper); n > 0 = DDIM over n evenly spaced steps
    # of the same network (K divisible by n; DPPO's ddim_steps): K/n times fewer denoiser calls
    # per action. DDIM sampling is deterministic (eta = 0) except in fine-tuning rollouts, which
    # explore with eta = 1. Set it on a BC checkpoint (--policy.ddim_steps=5) or fine-tune with it
    # (--ppo.ddim_steps=5 --ppo.ft_denoising_steps=5).
    ddim_steps: int = 0
    # Clamp of the x_0 prediction while sampling (actions live in [-1, 1]).
    denoised_clip_value: float = 1.0
    # Lower bound of the sampling std of select_action / predict_action_chunk (0: the DDPM
    # posterior std, no noise at the last step; DPPO's deterministic evaluation). Fine-tuning
    # rollouts explore with their own floor (--ppo.min_sampling_denoising_std: 0.1, every step).
    min_sampling_denoising_std: float = 0.0
    # Denoising steps fine-tuned by diffusion PPO (DPPO's K'; 0 = a BC policy). When > 0 the
    # policy holds a frozen copy of the pretrained encoder and denoiser (``base``) that runs the
    # first steps of the chain; the trained ones run the last K' (of K, or of ddim_steps).
    ft_denoising_steps: int = 0

    # -- critic size, read by diffusion PPO (lerobot_crowdnav.rl.dppo) ------------------------------
    # The policy builds no critic; the field stays so that every saved config.json still loads
    # (draccus rejects unknown fields). V(z): MLP [256, 256, 256], Mish (paper).
    value_mlp_dims: tuple[int, ...] = (256, 256, 256)

    # -- training (paper: AdamW, lr 1e-3, weight decay 1e-6, batch 128) -------------------------
    optimizer_lr: float = 1e-3
    optimizer_weight_decay: float = 1e-6
    optimizer_betas: tuple[float, float] = (0.9, 0.999)
    # (k, noise) draws per observation in the denoising loss, sharing one crowd encoding (1: the
    # paper; more lowers the loss's variance for little compute: docs/performance.md).
    noise_draws: int = 1
    # Exponential moving average of the actor's weights, used for sampling (DPPO pretraining: 0.995).
    use_ema: bool = True
    ema_decay: float = 0.995
    # Start averaging after this many updates (DPPO: ema starts after a warm-up).
    ema_start_step: int = 100

    def __post_init__(self):
        super().__post_init__()
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {self.horizon}")
        if not 1 <= self.n_action_steps <= self.horizon:
            raise ValueError(f"n_action_steps must be in [1, horizon={self.horizon}], got {self.n_action_steps}")
        if self.n_obs_steps != 1:
            raise ValueError("PDPO conditions on the current observation only (n_obs_steps = 1)")
        if self.human_mlp_dims[-1] % self.attention_heads:
            raise ValueError("human_mlp_dims[-1] must be divisible by attention_heads")
        if self.noise_draws < 1:
            raise ValueError(f"noise_draws must be >= 1, got {self.noise_draws}")
        if self.num_diffusion_steps < 1:
            raise ValueError("num_diffusion_steps must be >= 1")
        if self.ddim_steps < 0 or (self.ddim_steps and self.num_diffusion_steps % self.ddim_steps):
            raise ValueError(f"ddim_steps must be 0 (DDPM) or divide num_diffusion_steps={self.num_diffusion_steps}, "
                             f"got {self.ddim_steps}")
        if not 0 <= self.ft_denoising_steps <= self.sampling_steps:
            raise ValueError(f"ft_denoising_steps must be in [0, {self.sampling_steps}] (the sampling steps), "
                             f"got {self.ft_denoising_steps}")
        if not 0 <= self.velocity_dropout <= 1:
            raise ValueError(f"velocity_dropout must be in [0, 1], got {self.velocity_dropout}")
        if not 0 < self.ema_decay < 1:
            raise ValueError("ema_decay must be in (0, 1)")

    @property
    def sampling_steps(self) -> int:
        """Reverse steps of one sample: ddim_steps, or K for DDPM."""
        return self.ddim_steps or self.num_diffusion_steps

    @property
    def state_dim(self) -> int:
        return obs_dim(self.num_humans, self.prediction_steps)

    @property
    def latent_dim(self) -> int:
        return self.latent_mlp_dims[-1]

    def validate_features(self) -> None:
        check_policy_features(self, "PDPO")

    def get_optimizer_preset(self) -> FusedAdamWConfig:
        return FusedAdamWConfig(lr=self.optimizer_lr, weight_decay=self.optimizer_weight_decay,
                                betas=self.optimizer_betas)

    def get_scheduler_preset(self) -> None:
        return None  # constant learning rate

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> list[int]:
        # The dataset returns actions t .. t+H-1 of the episode, with action_is_pad past its end.
        return list(range(self.horizon))

    @property
    def reward_delta_indices(self) -> None:
        return None
