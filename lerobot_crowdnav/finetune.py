"""Online diffusion-PPO fine-tuning of a pretrained PDPO policy (DPPO): ``lerobot-crowdnav-finetune``.

    lerobot-crowdnav-finetune --policy.path=outputs/train/bounded_pdpo/checkpoints/last/pretrained_model \\
        --env.task=BoundedCrowdNav-v0 --env_steps=12000000 --output_dir=outputs/finetune/bounded_pdpo
    lerobot-crowdnav-finetune --config_path=configs/finetune/bounded_pdpo.yaml [--resume=true]
    accelerate launch --num_processes=2 -m lerobot_crowdnav.finetune ...   # DDP, one env batch per process

One iteration: every process steps its ``num_envs`` envs ``ppo.n_steps`` times, executing the
first action of each sampled chunk (receding horizon) and storing the chain of the K' fine-tuned
denoising steps; then ``ppo.update_epochs`` epochs of minibatch updates (see docs/finetune.md
for every choice, the batch-size semantics included).

Data contract of a rollout (T = n_steps, B = num_envs, K' = ft_denoising_steps, H = horizon):
    states (T, B, 269)          normalized observation.state (the policy's preprocessor)
    chains (T, B, K'+1, H, 2)   x_{K'} .. x_0 of the sampled chunk, normalized action units
    rewards, terminated, done (T, B); final states of episodes that ended by timeout

Output directory:
    checkpoints/<env steps>/pretrained_model   the fine-tuned policy (value head and frozen base
                                               included), processors, finetune_config.json
    checkpoints/<env steps>/training_state     optimizers, counters, reward scalers, RNG and env
                                               states (``--resume=true``)
    checkpoints/last -> <latest>;  checkpoints/best/pretrained_model (best validation success)
    progress.jsonl (a record per iteration), tensorboard/, wandb/, training_curves.png
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from . import fault
from .cli import run_cli
from .config import SEED_SPLITS, CrowdSimConfig
from .envs import CrowdNavVectorEnv
from .eval import json_safe, run_episodes
from .metrics import compute_metrics
from .ppo import RunningRewardScaler, clip_coefficients, denoising_discounts, explained_variance, gae, ppo_losses
from .sim import EVENT_NAMES

OBS = "observation.state"


@dataclass
class PolicySource:
    # Pretrained PDPO checkpoint to fine-tune: a pretrained_model directory written by
    # lerobot-train (or by this command), or a hub-format model directory.
    path: Path | None = None


@dataclass
class PPOConfig:
    """Diffusion PPO (DPPO). Defaults: the PDPO paper's table; DPPO's values where it is silent."""

    # Denoising steps fine-tuned (K'): the last K' of the K-step chain; a frozen copy of the
    # pretrained nets runs the first K - K'.
    ft_denoising_steps: int = 10
    # Steps each env takes per iteration (rollout length).
    n_steps: int = 64
    # Env steps per minibatch; each brings its K' denoising transitions, so a minibatch holds
    # batch_size * K' (env step, denoising step) pairs (DPPO >= v0.6 counts pairs: 5,000 here).
    batch_size: int = 500
    # Passes over the iteration's data.
    update_epochs: int = 5
    actor_lr: float = 1e-4
    critic_lr: float = 1e-3
    # AdamW weight decay of both optimizers (DPPO: 0).
    weight_decay: float = 0.0
    # Discount and GAE lambda on environment steps.
    gamma: float = 0.99
    gae_lambda: float = 0.95
    # Advantage of denoising step i is multiplied by gamma_denoising ** (K'-1-i).
    gamma_denoising: float = 0.99
    # Per-denoising-step PPO clip: clip_ploss_coef_base at the noisiest fine-tuned step up to
    # clip_ploss_coef at the final one, exponential with rate clip_ploss_coef_rate.
    clip_ploss_coef: float = 0.01
    clip_ploss_coef_base: float = 0.001
    clip_ploss_coef_rate: float = 3.0
    # Value-loss coefficient (the value loss is 0.5 (V - return)^2).
    vf_coef: float = 0.5
    # Stop the iteration's remaining updates once the approximate KL exceeds this (0: never).
    target_kl: float = 1.0
    # Std floor of the rollout's denoising steps (exploration noise at every step, the last included).
    min_sampling_denoising_std: float = 0.1
    # Std floor in the transitions' log-probabilities.
    min_logprob_denoising_std: float = 0.1
    # Scale rewards by a running std of the discounted return, clipped to +-reward_clip.
    reward_scale_running: bool = True
    reward_clip: float = 10.0
    # First iterations train only the critic (it starts fresh).
    n_critic_warmup_itr: int = 2
    # Gradient-norm clip of each optimizer's parameters (0: none, DPPO's default).
    max_grad_norm: float = 0.0

    def validate(self) -> None:
        for name in ("n_steps", "batch_size", "update_epochs", "ft_denoising_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"--ppo.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("actor_lr", "critic_lr", "min_sampling_denoising_std", "min_logprob_denoising_std"):
            if not getattr(self, name) > 0:
                raise ValueError(f"--ppo.{name} must be > 0, got {getattr(self, name)}")
        for name in ("gamma", "gae_lambda", "gamma_denoising"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"--ppo.{name} must be in (0, 1], got {getattr(self, name)}")
        if not 0 < self.clip_ploss_coef_base <= self.clip_ploss_coef:
            raise ValueError("need 0 < --ppo.clip_ploss_coef_base <= --ppo.clip_ploss_coef")
        if self.target_kl < 0 or self.max_grad_norm < 0 or self.n_critic_warmup_itr < 0:
            raise ValueError("--ppo.target_kl, --ppo.max_grad_norm and --ppo.n_critic_warmup_itr must be >= 0")


@dataclass
class ValidationConfig:
    # Validate (deterministic sampling) every this many env steps, all processes together; also
    # before the first update and after the last. 0: only then.
    freq: int = 200_000
    # Validation episodes: the first n seeds of the val split (at most 100).
    n_episodes: int = 100


@dataclass
class WandBConfig:
    # Also log to Weights & Biases (TensorBoard event files are always written).
    enable: bool = False
    # offline (no account or network needed; `wandb sync` later), online or disabled.
    mode: str = "offline"
    project: str = "lerobot-crowdnav"


@dataclass
class FinetuneConfig:
    # --policy.path=<pretrained PDPO checkpoint>
    policy: PolicySource = field(default_factory=PolicySource)
    # Simulator: --env.task, --env.preset and any simulator field. Training mode by default
    # (compute_intrusion=false: the dynamics and rewards are the same, the intrusion metrics skipped).
    env: CrowdSimConfig = field(default_factory=lambda: CrowdSimConfig(compute_intrusion=False))
    # Envs stepped together by each process.
    num_envs: int = 64
    # Budget in environment steps, all processes together (paper: about 12 M).
    env_steps: int = 12_000_000
    ppo: PPOConfig = field(default_factory=PPOConfig)
    val: ValidationConfig = field(default_factory=ValidationConfig)
    # Write a checkpoint every this many env steps (and at the end).
    save_freq: int = 500_000
    # Seed of the policy's sampling noise, the critic's initialization and the minibatch order.
    seed: int = 1000
    # First train-split episode seed of process 0; process r starts at env_seed + r * 10,000,000
    # (the ORCA demonstrations use seeds from 0).
    env_seed: int = 500_000_000
    # Torch device; default: cuda when available, else cpu.
    device: str | None = None
    # Where checkpoints and logs go (default: outputs/finetune/<task>_<preset>).
    output_dir: Path | None = None
    # Continue the run in output_dir from its last checkpoint (same settings; env_steps may grow).
    resume: bool = False
    wandb: WandBConfig = field(default_factory=WandBConfig)

    def validate(self, world_size: int = 1) -> None:
        self.ppo.validate()
        if self.num_envs < 1:
            raise ValueError(f"--num_envs must be >= 1, got {self.num_envs}")
        if self.env_steps < 1 or self.save_freq < 1 or self.val.freq < 0:
            raise ValueError("--env_steps and --save_freq must be >= 1, --val.freq >= 0")
        if self.ppo.n_steps * self.num_envs < self.ppo.batch_size:
            raise ValueError(f"an iteration has {self.ppo.n_steps * self.num_envs} env steps per process, fewer than "
                             f"--ppo.batch_size={self.ppo.batch_size}")
        val_size = SEED_SPLITS["val"][1] - SEED_SPLITS["val"][0]
        if not 1 <= self.val.n_episodes <= val_size:
            raise ValueError(f"--val.n_episodes must be in [1, {val_size}], got {self.val.n_episodes}")
        lo, hi = SEED_SPLITS["train"]
        if not (lo <= self.env_seed and self.env_seed + world_size * 10_000_000 <= hi):
            raise ValueError(f"--env_seed must leave {world_size} blocks of 10,000,000 train seeds below {hi}")
        if self.wandb.mode not in ("offline", "online", "disabled"):
            raise ValueError(f"--wandb.mode must be offline, online or disabled, got {self.wandb.mode!r}")

    def steps_per_iteration(self, world_size: int) -> int:
        return self.ppo.n_steps * self.num_envs * world_size


# Settings that must not change when a run is resumed.
_RESUME_KEYS = ("env", "num_envs", "ppo", "seed", "env_seed")


def load_policy(path: Path, ft_steps: int, seed: int):
    """The policy to fine-tune and its processors. A BC checkpoint becomes a fine-tuning policy
    whose trained and frozen nets both start from its sampling (EMA) weights and whose critic
    starts fresh; a fine-tuned checkpoint is taken as it is."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.utils.import_utils import register_third_party_plugins

    path = Path(path)
    if not (path / "config.json").exists():
        raise FileNotFoundError(f"--policy.path={path}: no config.json (expected a pretrained_model directory)")
    kind = json.loads((path / "config.json").read_text()).get("type")
    if kind != "pdpo":
        raise ValueError(f"--policy.path={path} holds a {kind!r} policy; diffusion PPO fine-tunes PDPO ('pdpo')")
    register_third_party_plugins()
    cfg = PreTrainedConfig.from_pretrained(path)
    from lerobot_policy_pdpo.modeling_pdpo import PDPOPolicy

    cfg.device = "cpu"
    loaded = PDPOPolicy.from_pretrained(path, config=cfg)
    if cfg.ft_denoising_steps and cfg.ft_denoising_steps != ft_steps:
        raise ValueError(f"{path} was fine-tuned with ft_denoising_steps={cfg.ft_denoising_steps}, not {ft_steps}")
    if ft_steps > cfg.num_diffusion_steps:
        raise ValueError(f"--ppo.ft_denoising_steps={ft_steps} exceeds the policy's {cfg.num_diffusion_steps} steps")
    policy = loaded
    if not cfg.ft_denoising_steps:
        ft_cfg = copy.deepcopy(cfg)
        ft_cfg.use_ema, ft_cfg.ft_denoising_steps = False, ft_steps
        torch.manual_seed(seed)  # the fresh critic
        policy = PDPOPolicy(ft_cfg)
        encoder, denoiser = loaded._sampling_nets()
        for enc, den in ((policy.encoder, policy.denoiser), (policy.base["encoder"], policy.base["denoiser"])):
            enc.load_state_dict(encoder.state_dict())
            den.load_state_dict(denoiser.state_dict())
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(path))
    return policy, pre, post


def check_compatible(policy, sim_cfg: CrowdSimConfig) -> None:
    cfg = policy.config
    if (cfg.num_humans, cfg.prediction_steps) != (sim_cfg.num_humans, sim_cfg.prediction_steps) \
            or cfg.state_dim != sim_cfg.obs_dim:
        raise ValueError(f"the policy reads {cfg.state_dim}-float observations ({cfg.num_humans} humans, "
                         f"{cfg.prediction_steps} prediction steps); the env gives {sim_cfg.obs_dim} "
                         f"({sim_cfg.num_humans} humans, {sim_cfg.prediction_steps} prediction steps)")
    if cfg.n_action_steps != 1:
        raise ValueError("diffusion PPO executes the first action of each chunk (receding horizon): "
                         f"the policy has n_action_steps={cfg.n_action_steps}")


class ChainScorer(nn.Module):
    """An update's trainable computation as one module (what DDP wraps): the log-probabilities
    ``(M, K')`` of stored chains and V(s) ``(M,)``. The critic reads the shared encoder's latent
    through a stop-gradient, so a fresh critic cannot overwrite the pretrained features."""

    def __init__(self, policy, min_logprob_std: float):
        super().__init__()
        self.policy = policy
        self.min_logprob_std = min_logprob_std

    def forward(self, state: torch.Tensor, chain: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logp, z = self.policy.chain_log_prob(state, chain, self.min_logprob_std)
        return logp, self.policy.value(z.detach())


@dataclass
class Rollout:
    states: torch.Tensor  # (T, B, D) normalized
    chains: torch.Tensor  # (T, B, K'+1, H, 2)
    rewards: np.ndarray  # (T, B) raw env rewards
    scaled_rewards: np.ndarray  # (T, B) what the critic learns
    terminated: np.ndarray  # (T, B)
    done: np.ndarray  # (T, B) terminated or truncated
    final_states: dict[tuple[int, int], torch.Tensor]  # (t, b) -> normalized final obs of a timeout (cpu)
    next_state: torch.Tensor  # (B, D) normalized observation after the last step (cpu)
    episodes: list[dict]  # event, return, length of the episodes that ended

    def digest(self) -> str:
        """Fingerprint of the data an update sees (reproducibility checks across resumes)."""
        h = hashlib.sha256()
        for a in (self.states.numpy(), self.chains.numpy(), self.rewards, self.done):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()[:16]


class Trainer:
    """The fine-tuning loop of one process (rank); rank 0 also validates, logs and saves."""

    def __init__(self, cfg: FinetuneConfig):
        from accelerate import Accelerator

        device = cfg.device or ("cuda" if torch.cuda.is_available() else "cpu")
        self.accelerator = acc = Accelerator(cpu=device == "cpu")
        self.rank, self.world = acc.process_index, acc.num_processes
        self.main = acc.is_main_process
        self.device = acc.device
        cfg.validate(self.world)
        self.cfg = cfg
        self.sim_cfg = cfg.env.resolve()
        self.out = Path(cfg.output_dir or f"outputs/finetune/{self.sim_cfg.task}_{self.sim_cfg.preset}")
        if self.device.type == "cpu":
            torch.set_num_threads(max(1, (os.cpu_count() or 1) // self.world))
        last = self.out / "checkpoints" / "last"
        # --resume=true before the first checkpoint (killed early): start over from --policy.path.
        self.resumed = cfg.resume and last.exists()
        if self.resumed:
            self._check_resume_settings(last / "pretrained_model" / "finetune_config.json")
            source = last / "pretrained_model"
        else:
            if not cfg.resume and self.out.exists() and any(self.out.iterdir()):
                raise FileExistsError(f"{self.out} exists; pass --resume=true to continue its run or choose another --output_dir")
            if cfg.policy.path is None:
                raise ValueError("--policy.path=<pretrained PDPO checkpoint> is required")
            source = cfg.policy.path
        policy, self.pre, self.post = load_policy(source, cfg.ppo.ft_denoising_steps, cfg.seed)
        # lerobot-train's record of the pretraining, carried into every checkpoint (provenance)
        self.pretrain_config = Path(source) / "train_config.json"
        check_compatible(policy, self.sim_cfg)
        self.policy = policy.to(self.device).eval()  # eval: no dropout, so rollout and update agree
        self.ft = cfg.ppo.ft_denoising_steps
        ppo = cfg.ppo
        actor = [p for n, p in policy.named_parameters() if n.split(".")[0] in ("encoder", "denoiser")]
        self.actor_opt = torch.optim.AdamW(actor, lr=ppo.actor_lr, weight_decay=ppo.weight_decay)
        self.critic_opt = torch.optim.AdamW(policy.value.parameters(), lr=ppo.critic_lr, weight_decay=ppo.weight_decay)
        self.scorer, self.actor_opt, self.critic_opt = acc.prepare(
            ChainScorer(self.policy, ppo.min_logprob_denoising_std), self.actor_opt, self.critic_opt)
        self.env = CrowdNavVectorEnv(cfg.num_envs, config=self.sim_cfg)
        self.scaler = RunningRewardScaler(cfg.num_envs, ppo.gamma, ppo.reward_clip)
        self.generator = torch.Generator(device=self.device).manual_seed(cfg.seed * 1000 + self.rank)
        self.rng = np.random.default_rng([cfg.seed, self.rank])
        self.clip = torch.tensor(clip_coefficients(self.ft, ppo.clip_ploss_coef_base, ppo.clip_ploss_coef,
                                                   ppo.clip_ploss_coef_rate), dtype=torch.float32, device=self.device)
        self.discount = torch.tensor(denoising_discounts(self.ft, ppo.gamma_denoising), dtype=torch.float32,
                                     device=self.device)
        self.iteration, self.env_steps, self.best_val_sr = 0, 0, -1.0
        self.obs, _ = self.env.reset(seed=cfg.env_seed + self.rank * 10_000_000)
        if self.resumed:
            self._load_training_state(last / "training_state")
        self.val_env = CrowdNavVectorEnv(cfg.val.n_episodes, config=self.sim_cfg) if self.main else None

    # -- settings and checkpoints ----------------------------------------------------------------
    def _config_dict(self) -> dict:
        return json.loads(json.dumps(draccus.encode(self.cfg), default=str))

    def _check_resume_settings(self, saved_path: Path) -> None:
        saved = json.loads(saved_path.read_text())
        now = self._config_dict()
        changed = [k for k in _RESUME_KEYS if saved.get(k) != now.get(k)]
        if saved.get("world_size", 1) != self.world:
            changed.append(f"number of processes ({saved.get('world_size', 1)} -> {self.world})")
        if changed:
            raise ValueError(f"--resume=true with different settings than the saved run: {', '.join(changed)}")

    def _save_checkpoint(self) -> Path:
        acc = self.accelerator
        root = self.out / "checkpoints"
        name = f"{self.env_steps:0{max(9, len(str(self.cfg.env_steps)))}d}"
        staging = root / f".{name}.tmp"
        state = staging / "training_state"
        if self.main:
            shutil.rmtree(staging, ignore_errors=True)
            state.mkdir(parents=True)
            self._save_policy(staging / "pretrained_model")
            fault.point("finetune.checkpoint_writing")
            torch.save({"actor_opt": self.actor_opt.state_dict(), "critic_opt": self.critic_opt.state_dict(),
                        "iteration": self.iteration, "env_steps": self.env_steps, "best_val_sr": self.best_val_sr},
                       state / "optimizers.pt")
        acc.wait_for_everyone()
        np.savez(state / f"env_rank{self.rank}.npz", **self.env.state_dict())
        (state / f"rng_rank{self.rank}.json").write_text(json.dumps({
            "numpy": self.rng.bit_generator.state, "torch": self.generator.get_state().tolist(),
            "scaler": self.scaler.state_dict(), "obs_shape": list(self.obs.shape)}))
        acc.wait_for_everyone()
        final = root / name
        if self.main:  # complete, then in place, then named last: a kill never leaves a partial last
            fault.replace_dir(staging, final)
            fault.point("finetune.checkpoint_renamed")
            link = root / ".last.tmp"
            link.unlink(missing_ok=True)
            link.symlink_to(name)
            link.replace(root / "last")
            fault.point("finetune.last_linked")
        acc.wait_for_everyone()
        return final

    def _save_policy(self, path: Path) -> None:
        policy = self.accelerator.unwrap_model(self.scorer).policy
        policy.save_pretrained(path)
        self.pre.save_pretrained(path)
        self.post.save_pretrained(path)
        if self.pretrain_config.exists():
            shutil.copy2(self.pretrain_config, path / "train_config.json")
        (path / "finetune_config.json").write_text(json.dumps(
            {**self._config_dict(), "world_size": self.world, "env_steps_done": self.env_steps}, indent=2))

    def _load_training_state(self, state: Path) -> None:
        saved = torch.load(state / "optimizers.pt", map_location=self.device, weights_only=True)
        self.actor_opt.load_state_dict(saved["actor_opt"])
        self.critic_opt.load_state_dict(saved["critic_opt"])
        self.iteration, self.env_steps, self.best_val_sr = saved["iteration"], saved["env_steps"], saved["best_val_sr"]
        with np.load(state / f"env_rank{self.rank}.npz") as env_state:
            self.env.load_state_dict(dict(env_state))
        self.obs = self.env.sim.obs.copy()
        rng = json.loads((state / f"rng_rank{self.rank}.json").read_text())
        self.rng.bit_generator.state = rng["numpy"]
        self.generator.set_state(torch.tensor(rng["torch"], dtype=torch.uint8))
        self.scaler.load_state_dict(rng["scaler"])

    # -- rollout ---------------------------------------------------------------------------------
    @torch.no_grad()
    def _normalize(self, obs: np.ndarray) -> torch.Tensor:
        return self.pre({OBS: torch.as_tensor(obs, dtype=torch.float32)})[OBS].to(self.device)

    @torch.no_grad()
    def _act(self, state: torch.Tensor, explore: bool, generator: torch.Generator):
        """First actions (B, 2) in m/s (receding horizon) and, when exploring, the chains."""
        if explore:
            chunk, chain = self.policy.sample(state, generator=generator, return_chain=True,
                                              exploration_std=self.cfg.ppo.min_sampling_denoising_std)
        else:
            chunk, chain = self.policy.sample(state, generator=generator), None
        return self.post(chunk[:, 0]).cpu().numpy().astype(np.float64), chain

    def rollout(self) -> Rollout:
        T, B = self.cfg.ppo.n_steps, self.cfg.num_envs
        ppo = self.cfg.ppo
        states = torch.empty(T, B, self.sim_cfg.obs_dim, device=self.device)
        chains = torch.empty(T, B, self.ft + 1, self.policy.config.horizon, 2, device=self.device)
        rewards, scaled = np.zeros((T, B)), np.zeros((T, B))
        terminated, done = np.zeros((T, B), bool), np.zeros((T, B), bool)
        final_states, episodes = {}, []
        for t in range(T):
            states[t] = self._normalize(self.obs)
            actions, chains[t] = self._act(states[t], True, self.generator)
            self.obs, reward, term, trunc, info = self.env.step(actions)
            rewards[t], terminated[t], done[t] = reward, term, term | trunc
            scaled[t] = self.scaler(reward, done[t]) if ppo.reward_scale_running else reward
            for b in np.flatnonzero(trunc):
                final_states[(t, b)] = self._normalize(info["final_obs"][b:b + 1])[0].cpu()
            if "final_info" in info:
                fi = info["final_info"]
                for b in np.flatnonzero(info["_final_info"]):
                    episodes.append({"event": EVENT_NAMES[int(fi["event"][b])], "return": float(fi["return"][b]),
                                     "length": int(fi["length"][b])})
        return Rollout(states.cpu(), chains.cpu(), rewards, scaled, terminated, done, final_states,
                       self._normalize(self.obs).cpu(), episodes)

    # -- update ----------------------------------------------------------------------------------
    def update(self, ro: Rollout) -> dict[str, float]:
        ppo, acc = self.cfg.ppo, self.accelerator
        T, B = ro.rewards.shape
        n = T * B
        states = ro.states.reshape(n, -1).to(self.device)
        chains = ro.chains.reshape(n, *ro.chains.shape[2:]).to(self.device)
        mb = ppo.batch_size
        first_perm = self.rng.permutation(n)
        # Old log-probabilities and values under the pre-update weights, computed over the first
        # epoch's minibatch partition and with autograd on (no_grad would switch attention to its
        # fused kernel): the first minibatch's ratio is then exactly 1.
        old_logp, values = torch.empty(n, self.ft, device=self.device), torch.empty(n, device=self.device)
        scorer = acc.unwrap_model(self.scorer)
        for i in range(0, n, mb):
            idx = torch.as_tensor(first_perm[i:i + mb], device=self.device)
            logp, value = scorer(states[idx], chains[idx])
            old_logp[idx], values[idx] = logp.detach(), value.detach()
        # Bootstrap values: the states after the last step and the final states of timeouts.
        keys = list(ro.final_states)
        boot = torch.cat([ro.next_state, *(ro.final_states[k][None] for k in keys)]).to(self.device)
        with torch.no_grad():
            v_boot = scorer.policy.value(scorer.policy.encoder(boot)).cpu().numpy()
        v = values.cpu().numpy().reshape(T, B)
        next_values = np.concatenate([v[1:], v_boot[None, :B]], axis=0)
        for (t, b), value in zip(keys, v_boot[B:], strict=True):
            next_values[t, b] = value
        adv, ret = gae(ro.scaled_rewards, v, next_values, ro.terminated.astype(float), ro.done.astype(float),
                       ppo.gamma, ppo.gae_lambda)
        adv_t = torch.as_tensor(adv.reshape(n), dtype=torch.float32, device=self.device)
        ret_t = torch.as_tensor(ret.reshape(n), dtype=torch.float32, device=self.device)
        warmup = self.iteration < ppo.n_critic_warmup_itr
        stats: dict[str, list[float]] = {}
        epochs_done, stop = 0, False
        for epoch in range(ppo.update_epochs):
            perm = first_perm if epoch == 0 else self.rng.permutation(n)
            for start in range(0, n - mb + 1, mb):
                idx = torch.as_tensor(perm[start:start + mb], device=self.device)
                new_logp, new_v = self.scorer(states[idx], chains[idx])
                losses = ppo_losses(new_logp, old_logp[idx], adv_t[idx], self.clip, self.discount, new_v, ret_t[idx])
                # During the critic warm-up the policy loss is kept at zero weight, so that every
                # parameter still gets a (zero) gradient, as DDP requires.
                loss = (0.0 if warmup else 1.0) * losses["policy_loss"] + ppo.vf_coef * losses["value_loss"]
                self.actor_opt.zero_grad(set_to_none=True)
                self.critic_opt.zero_grad(set_to_none=True)
                acc.backward(loss)
                if ppo.max_grad_norm:
                    acc.clip_grad_norm_([p for g in self.actor_opt.param_groups for p in g["params"]], ppo.max_grad_norm)
                    acc.clip_grad_norm_(list(scorer.policy.value.parameters()), ppo.max_grad_norm)
                if not warmup:
                    self.actor_opt.step()
                self.critic_opt.step()
                for k, val in losses.items():
                    stats.setdefault(k, []).append(float(val.detach()))
                kl = acc.reduce(losses["approx_kl"].detach().clone(), reduction="mean")
                if ppo.target_kl and float(kl) > ppo.target_kl:
                    stop = True  # like DPPO: the step that crossed the target is kept
                    break
            epochs_done += 1
            if stop:
                break
        out = {f"loss/{k}" if k.endswith("loss") else k: float(np.mean(v)) for k, v in stats.items()}
        out["update_epochs"] = epochs_done
        out["explained_variance"] = explained_variance(v.reshape(-1), ret.reshape(-1))
        out["critic_warmup"] = float(warmup)
        return out

    # -- validation and logging ------------------------------------------------------------------
    def validate(self) -> dict[str, float]:
        """Deterministic sampling (no noise at the last denoising step) on the validation seeds."""
        generator = torch.Generator(device=self.device).manual_seed(0)
        actor = lambda obs, fresh: self._act(self._normalize(obs), False, generator)[0]  # noqa: E731
        records = run_episodes(self.val_env, actor, "val", self.cfg.val.n_episodes, progress=False)
        m = compute_metrics(records, self.sim_cfg.dt)
        return {"val/success_rate": m["sr"], "val/collision_rate": m["cr"], "val/timeout_rate": m["tr"],
                "val/navigation_time": m["nt"], "val/episode_return": float(np.mean([r.episode_return for r in records]))}

    def _episode_stats(self, episodes: list[dict]) -> dict[str, float | None]:
        counts = torch.tensor([len(episodes), *[sum(e["event"] == ev for e in episodes) for ev in
                               ("success", "human_collision", "wall_collision", "timeout")],
                               sum(e["return"] for e in episodes), sum(e["length"] for e in episodes)],
                              dtype=torch.float64, device=self.device)
        c = self.accelerator.reduce(counts, reduction="sum").cpu().tolist()
        if not c[0]:
            return {"train/episodes": 0}
        return {"train/episodes": int(c[0]), "train/success_rate": c[1] / c[0], "train/human_collision_rate": c[2] / c[0],
                "train/wall_collision_rate": c[3] / c[0], "train/timeout_rate": c[4] / c[0],
                "train/episode_return": c[5] / c[0], "train/episode_length": c[6] / c[0]}

    # -- the loop --------------------------------------------------------------------------------
    def run(self) -> dict:
        cfg, acc = self.cfg, self.accelerator
        per_iter = cfg.steps_per_iteration(self.world)
        progress = self.out / "progress.jsonl"
        writer = wandb_run = None
        records: list[dict] = []
        if self.main:
            self.out.mkdir(parents=True, exist_ok=True)
            if self.resumed and progress.exists():  # keep the history up to the checkpoint being resumed
                records = [r for r in map(json.loads, progress.read_text().splitlines()) if r["iteration"] <= self.iteration]
            progress.write_text("".join(json.dumps(r) + "\n" for r in records))
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(self.out / "tensorboard", purge_step=self.iteration + 1 if self.resumed else 0)
            if cfg.wandb.enable:
                import wandb

                wandb_run = wandb.init(project=cfg.wandb.project, mode=cfg.wandb.mode, dir=str(self.out),
                                       config=self._config_dict(), name=self.out.name, id=self.out.name.replace("/", "_"),
                                       resume="allow")
        bar = tqdm(total=cfg.env_steps, initial=min(self.env_steps, cfg.env_steps), unit="env-step",
                   desc="diffusion PPO", disable=not self.main, dynamic_ncols=True)

        def log(record: dict) -> None:
            if not self.main:
                return
            records.append(record)
            with progress.open("a") as f:
                f.write(json.dumps(json_safe(record), allow_nan=False) + "\n")
            for k, val in record.items():
                if isinstance(val, (int, float)) and k not in ("iteration", "env_steps") and math.isfinite(val):
                    writer.add_scalar(k, val, record["env_steps"])
            writer.flush()
            if wandb_run is not None:
                wandb_run.log({k: v for k, v in record.items() if isinstance(v, (int, float))}, step=record["env_steps"])

        if self.iteration == 0 and self.main:
            val = self.validate()  # the pretrained policy
            self._maybe_best(val)
            log({"iteration": 0, "env_steps": 0, **val})
        acc.wait_for_everyone()
        while self.env_steps < cfg.env_steps:
            t0 = time.perf_counter()
            ro = self.rollout()
            t1 = time.perf_counter()
            record = {"iteration": self.iteration + 1, "env_steps": self.env_steps + per_iter, "rollout_digest": ro.digest()}
            record.update(self._episode_stats(ro.episodes))
            record.update(self.update(ro))
            t2 = time.perf_counter()
            self.iteration += 1
            self.env_steps += per_iter
            record.update({"perf/rollout_env_steps_per_s": per_iter / (t1 - t0),
                           "perf/update_env_steps_per_s": per_iter / (t2 - t1),
                           "perf/env_steps_per_s": per_iter / (t2 - t0)})
            last = self.env_steps >= cfg.env_steps
            if self.main and (last or (cfg.val.freq and self.env_steps // cfg.val.freq > (self.env_steps - per_iter) // cfg.val.freq)):
                val = self.validate()
                record.update(val)
                self._maybe_best(val)
            log(record)
            bar.update(min(per_iter, cfg.env_steps - bar.n))
            if self.main:
                bar.set_postfix({k.split("/")[-1]: f"{record[k]:.3f}" for k in ("train/success_rate", "val/success_rate") if k in record})
            acc.wait_for_everyone()
            if last or self.env_steps // cfg.save_freq > (self.env_steps - per_iter) // cfg.save_freq:
                self._save_checkpoint()
        bar.close()
        result = {"output_dir": str(self.out), "env_steps": self.env_steps, "best_val_success_rate": self.best_val_sr}
        if self.main:
            writer.close()
            if wandb_run is not None:
                wandb_run.finish()
            from .plots import plot_finetune_curves

            plot_finetune_curves({self.out.name: records}, self.out / "training_curves.png")
            procs = "1 process" if self.world == 1 else f"{self.world} processes ({acc.distributed_type.value})"
            print(f"\nfine-tuned {self.env_steps} env steps on {procs}; "
                  f"best validation success rate {self.best_val_sr:.3f}; checkpoints in {self.out / 'checkpoints'}")
        return result

    def _maybe_best(self, val: dict) -> None:
        sr = val["val/success_rate"]
        if sr > self.best_val_sr:
            self.best_val_sr = sr
            staging = self.out / "checkpoints" / ".best.tmp"
            shutil.rmtree(staging, ignore_errors=True)
            self._save_policy(staging / "pretrained_model")
            (staging / "best.json").write_text(json.dumps({"env_steps": self.env_steps, "iteration": self.iteration, **val}, indent=2))
            fault.replace_dir(staging, self.out / "checkpoints" / "best")


def finetune(cfg: FinetuneConfig) -> dict:
    return Trainer(cfg).run()


def main(argv: list[str] | None = None) -> None:
    run_cli(FinetuneConfig, finetune, argv, "rerun the same command with --resume=true to continue from the last checkpoint")


if __name__ == "__main__":
    main()
