"""Running a robot policy on fixed episode seeds: what every evaluation shares.

``run_episodes`` steps a batch of envs on the first seeds of a split and returns one
``EpisodeRecord`` per seed; ``LearnedPolicy`` drives the batch with a lerobot policy checkpoint;
``json_safe`` makes metrics strict JSON. Used by the eval CLI, the figures, the baselines and
the fine-tuning validation (``rl/validation.py``), which all sit above this module.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..checkpoint_files import POLICY_CONFIG
from ..layout import SENTINEL, check_sentinel
from ..sim.config import split_seeds
from ..sim.envs import CrowdNavVectorEnv
from .metrics import EpisodeRecord


class LearnedPolicy:
    """A lerobot policy driving a batch of envs: observation.state in, (B, 2) velocities in m/s
    out. Chunks are sampled for the whole batch and each slot executes its first
    ``n_action_steps`` actions (1: replan every step) before taking the next chunk. A recurrent
    policy (``policy.recurrent``, e.g. crowdnavpp) acts every step and restarts the memory of the
    slots whose episode just began (``predict_action_chunk(..., episode_start=fresh)``)."""

    def __init__(self, path: Path, device: str, obs_dim: int, seed: int = 0, use_ema: bool = True,
                 ddim_steps: int | None = None, sentinel: float = SENTINEL):
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors
        from lerobot.utils.import_utils import register_third_party_plugins

        path = Path(path)
        if not (path / POLICY_CONFIG).exists():
            raise FileNotFoundError(f"--policy.path={path}: no config.json (expected a pretrained_model directory)")
        register_third_party_plugins()
        cfg = PreTrainedConfig.from_pretrained(path)
        cfg.device = device
        state = cfg.input_features.get("observation.state")
        if state is None or tuple(state.shape) != (obs_dim,):
            raise ValueError(f"policy at {path} expects observation.state of shape "
                             f"{None if state is None else tuple(state.shape)}, the env gives ({obs_dim},)")
        check_sentinel(cfg, sentinel)
        if ddim_steps is not None:
            if not hasattr(cfg, "ddim_steps"):
                raise ValueError(f"--policy.ddim_steps is for PDPO; {path} is a {cfg.type!r} policy")
            if cfg.ft_denoising_steps and ddim_steps != cfg.ddim_steps:
                raise ValueError(f"--policy.ddim_steps={ddim_steps}: {path} was fine-tuned with ddim_steps={cfg.ddim_steps} "
                                 "and samples only that way")
            cfg = dataclasses.replace(cfg, ddim_steps=ddim_steps)  # validated like any config
        self.torch = torch
        self.policy = get_policy_class(cfg.type).from_pretrained(path, config=cfg).eval()
        if not use_ema and hasattr(cfg, "use_ema"):
            cfg.use_ema = False  # after loading: the checkpoint's EMA weights stay, unused
        self.pre, self.post = make_pre_post_processors(cfg, pretrained_path=str(path), **on_device(device))
        self.n_action_steps = getattr(cfg, "n_action_steps", 1)
        self.recurrent = bool(getattr(self.policy, "recurrent", False))
        self.generator = torch.Generator(device=device).manual_seed(seed)
        self.chunk: np.ndarray | None = None
        self.index: np.ndarray | None = None

    def __call__(self, obs: np.ndarray, fresh: np.ndarray) -> np.ndarray:
        b = obs.shape[0]
        if self.chunk is None or self.chunk.shape[0] != b:
            self.chunk, self.index = None, np.zeros(b, np.int64)
            fresh = np.ones(b, bool)
        if self.recurrent:  # every step, the memory restarted where an episode begins
            with self.torch.inference_mode():
                batch = self.pre({"observation.state": self.torch.as_tensor(obs, dtype=self.torch.float32)})
                chunk = self.policy.predict_action_chunk(batch, generator=self.generator,
                                                         episode_start=self.torch.as_tensor(fresh))
                self.chunk = self.post(chunk).cpu().numpy()
            return self.chunk[:, 0]
        need = fresh | (self.index >= self.n_action_steps)
        if need.any():
            with self.torch.inference_mode():
                batch = self.pre({"observation.state": self.torch.as_tensor(obs, dtype=self.torch.float32)})
                chunk = self.policy.predict_action_chunk(batch, generator=self.generator)
                chunk = self.post(chunk).cpu().numpy()
            self.chunk = chunk if self.chunk is None else np.where(need[:, None, None], chunk, self.chunk)
            self.index[need] = 0
        actions = self.chunk[np.arange(b), self.index]
        self.index += 1
        return actions


def run_episodes(env: CrowdNavVectorEnv, policy, split: str, n_episodes: int,
                 progress: bool = True, label: str = "") -> list[EpisodeRecord]:
    """Run the first ``n_episodes`` seeds of ``split``; records by seed. ``policy`` is a built-in
    name ("orca", "straight") or a callable ``(obs (B, D), fresh (B,)) -> actions (B, 2)``, fresh
    marking the slots whose episode just started."""
    seeds = split_seeds(split, n_episodes)
    wanted = set(seeds)
    obs, _ = env.reset(seed=seeds[0])
    fresh = np.ones(env.num_envs, bool)
    records: dict[int, EpisodeRecord] = {}
    bar = tqdm(total=n_episodes, desc=f"eval {label or policy}", unit="ep", disable=not progress)
    while len(records) < n_episodes:
        actions = policy(obs, fresh) if callable(policy) else env.expert_actions(policy)
        obs, _, terminated, truncated, info = env.step(actions)
        fresh = terminated | truncated
        if "final_info" in info:
            for b in np.flatnonzero(info["_final_info"]):
                rec = EpisodeRecord.from_final_info(info["final_info"], b)
                if rec.seed in wanted and rec.seed not in records:
                    records[rec.seed] = rec
                    bar.update(1)
            if records:  # the first episodes to end may all be extra seeds of a wider env
                bar.set_postfix(sr=f"{np.mean([r.event == 'success' for r in records.values()]):.3f}")
    bar.close()
    return [records[s] for s in seeds]


def on_device(device: str) -> dict:
    """``make_pre_post_processors`` overrides that put a saved preprocessor's inputs on ``device``:
    its device step otherwise keeps the device the checkpoint was trained on (a GPU-trained policy
    would fail on a CPU machine), as ``lerobot-eval`` and ``lerobot-train`` override it too."""
    return {"preprocessor_overrides": {"device_processor": {"device": str(device)}}}


def json_safe(value):
    """Strict JSON: undefined means (NaN, e.g. NT without a success) become null."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
