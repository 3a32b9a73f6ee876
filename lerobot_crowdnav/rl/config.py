"""PPO settings: ``PPOConfig`` for any actor-critic, ``DiffusionPPOConfig`` adds what only a
diffusion policy has (DPPO). Both are the ``--ppo.*`` flags of lerobot-crowdnav-finetune."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .ppo import clip_coefficients, denoising_discounts


@dataclass
class PPOConfig:
    """PPO. Defaults: the PDPO paper's table; DPPO's values where it is silent."""

    # Steps each env takes per iteration (rollout length).
    n_steps: int = 64
    # Env steps per minibatch (a recurrent policy gets batch_size // n_steps whole env sequences).
    # A diffusion decision brings its K' denoising transitions, so a PDPO minibatch holds
    # batch_size * K' (env step, denoising step) pairs (DPPO >= v0.6 counts pairs: 5,000 here).
    batch_size: int = 500
    # Passes over the iteration's data.
    update_epochs: int = 5
    # Learning rate of the actor (AdamW).
    actor_lr: float = 1e-4
    # Learning rate of the critic (AdamW).
    critic_lr: float = 1e-3
    # AdamW weight decay of both optimizers (DPPO: 0).
    weight_decay: float = 0.0
    # Discount on environment steps.
    gamma: float = 0.99
    # GAE lambda on environment steps.
    gae_lambda: float = 0.95
    # PPO clip of the probability ratio (of the final denoising step for a diffusion policy).
    clip_ploss_coef: float = 0.01
    # Value-loss coefficient (the value loss is 0.5 (V - return)^2).
    vf_coef: float = 0.5
    # Stop the iteration's remaining updates once the approximate KL exceeds this (0: never).
    target_kl: float = 1.0
    # Scale rewards by a running std of the discounted return, clipped to +-reward_clip.
    reward_scale_running: bool = True
    # The clip of the scaled rewards.
    reward_clip: float = 10.0
    # First iterations train only the critic (it starts fresh).
    n_critic_warmup_itr: int = 2
    # Gradient-norm clip of each optimizer's parameters (0: none, DPPO's default).
    max_grad_norm: float = 0.0
    # Adam's epsilon, both optimizers (PyTorch's default 1e-8; CrowdNav++: 1e-5).
    adam_eps: float = 1e-8
    # Clip the value loss around the pre-update values by +-clip_ploss_coef (OpenAI baselines,
    # CrowdNav++); false: the plain 0.5 (V - return)^2.
    clip_vloss: bool = False
    # Advantage normalization: per "minibatch" (CleanRL) or once over each process's "rollout"
    # (CrowdNav++, eps 1e-5).
    norm_adv: str = "minibatch"
    # Bootstrap a timeout from V of its final observation (true); false: a timeout is terminal,
    # as CrowdNav++ trains (use_proper_time_limits=False).
    bootstrap_timeouts: bool = True

    def validate(self) -> None:
        for name in ("n_steps", "batch_size", "update_epochs"):
            if getattr(self, name) < 1:
                raise ValueError(f"--ppo.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("actor_lr", "critic_lr", "clip_ploss_coef"):
            if not getattr(self, name) > 0:
                raise ValueError(f"--ppo.{name} must be > 0, got {getattr(self, name)}")
        for name in ("gamma", "gae_lambda"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"--ppo.{name} must be in (0, 1], got {getattr(self, name)}")
        if self.target_kl < 0 or self.max_grad_norm < 0 or self.n_critic_warmup_itr < 0:
            raise ValueError("--ppo.target_kl, --ppo.max_grad_norm and --ppo.n_critic_warmup_itr must be >= 0")
        if not self.adam_eps > 0:
            raise ValueError(f"--ppo.adam_eps must be > 0, got {self.adam_eps}")
        if self.norm_adv not in ("minibatch", "rollout"):
            raise ValueError(f"--ppo.norm_adv must be minibatch or rollout, got {self.norm_adv!r}")
        if self.norm_adv == "minibatch" and self.batch_size < 2:
            raise ValueError("--ppo.norm_adv=minibatch normalizes each minibatch's advantages by their std: "
                             f"--ppo.batch_size must be >= 2, got {self.batch_size}")
        if not self.reward_clip > 0:
            raise ValueError(f"--ppo.reward_clip must be > 0, got {self.reward_clip}")

    def clip_per_part(self) -> np.ndarray:
        """PPO clip of each scored part of a decision, ``(n,)``: one part here."""
        return np.array([self.clip_ploss_coef])

    def advantage_weights(self) -> np.ndarray:
        """Weight of the advantage for each scored part of a decision, ``(n,)``."""
        return np.ones(1)


@dataclass
class DiffusionPPOConfig(PPOConfig):
    """Diffusion PPO (DPPO): a decision is a sampled chunk, scored as its K' fine-tuned
    denoising transitions, each with its own clip and advantage discount."""

    # Denoising steps fine-tuned (K'): the last K' of the chain; a frozen copy of the pretrained
    # nets runs the ones before.
    ft_denoising_steps: int = 10
    # Sample and fine-tune with DDIM over this many steps (0: DDPM over the policy's K; DPPO's
    # ddim_steps): e.g. --ppo.ddim_steps=5 --ppo.ft_denoising_steps=5 runs 5 denoiser calls per
    # action instead of 20 and scores 5 transitions instead of 10. Rollouts explore with eta = 1.
    ddim_steps: int = 0
    # Advantage of denoising step i is multiplied by gamma_denoising ** (K'-1-i).
    gamma_denoising: float = 0.99
    # Per-denoising-step PPO clip: clip_ploss_coef_base at the noisiest fine-tuned step up to
    # clip_ploss_coef at the final one, exponential with rate clip_ploss_coef_rate.
    clip_ploss_coef_base: float = 0.001
    # The rate of that exponential.
    clip_ploss_coef_rate: float = 3.0
    # Std floor of the rollout's denoising steps (exploration noise at every step, the last included).
    min_sampling_denoising_std: float = 0.1
    # Std floor in the transitions' log-probabilities.
    min_logprob_denoising_std: float = 0.1
    # Keep the pretrained crowd encoder fixed and fine-tune the denoiser only (not in the paper).
    # The encoder costs far more than the denoiser, so each state's latent is computed once, in the
    # rollout, and reused by every update epoch: docs/performance.md measures what it saves.
    freeze_encoder: bool = False
    # What the critic reads: "latent" (the paper's V(z), the actor's encoding through a
    # stop-gradient), "state" (the normalized observation: DPPO's critic for state inputs) or
    # "latent+state". A frozen BC encoding is not trained to tell good states from bad ones:
    # docs/finetune.md measures the critics' explained variance.
    critic_input: str = "latent"
    # What a transition's log-probability averages over: the whole sampled "chunk" (H x 2 elements,
    # the paper's appendix) or the "executed" action only (the chunk's first: DPPO's code keeps the
    # executed actions). With "chunk" the H - 1 unexecuted actions dilute the executed one's ratio, so
    # the same clip can let it move up to H times further (docs/finetune.md measures both).
    logprob_actions: str = "chunk"

    def validate(self) -> None:
        super().validate()
        if self.critic_input not in ("latent", "state", "latent+state"):
            raise ValueError(f"--ppo.critic_input must be latent, state or latent+state, got {self.critic_input!r}")
        if self.logprob_actions not in ("chunk", "executed"):
            raise ValueError(f"--ppo.logprob_actions must be chunk or executed, got {self.logprob_actions!r}")
        if self.ft_denoising_steps < 1:
            raise ValueError(f"--ppo.ft_denoising_steps must be >= 1, got {self.ft_denoising_steps}")
        if self.ddim_steps < 0 or 0 < self.ddim_steps < self.ft_denoising_steps:
            raise ValueError(f"--ppo.ddim_steps must be 0 (DDPM) or >= --ppo.ft_denoising_steps={self.ft_denoising_steps}, "
                             f"got {self.ddim_steps}")
        for name in ("min_sampling_denoising_std", "min_logprob_denoising_std"):
            if not getattr(self, name) > 0:
                raise ValueError(f"--ppo.{name} must be > 0, got {getattr(self, name)}")
        if not 0 < self.gamma_denoising <= 1:
            raise ValueError(f"--ppo.gamma_denoising must be in (0, 1], got {self.gamma_denoising}")
        if not 0 < self.clip_ploss_coef_base <= self.clip_ploss_coef:
            raise ValueError("need 0 < --ppo.clip_ploss_coef_base <= --ppo.clip_ploss_coef")
        try:
            with np.errstate(over="ignore", invalid="ignore"):
                finite = bool(np.isfinite(self.clip_per_part()).all())
        except OverflowError:
            finite = False
        if not finite:
            raise ValueError(f"--ppo.clip_ploss_coef_rate={self.clip_ploss_coef_rate} overflows the clip schedule")

    def clip_per_part(self) -> np.ndarray:
        return clip_coefficients(self.ft_denoising_steps, self.clip_ploss_coef_base, self.clip_ploss_coef,
                                 self.clip_ploss_coef_rate)

    def advantage_weights(self) -> np.ndarray:
        return denoising_discounts(self.ft_denoising_steps, self.gamma_denoising)
