"""The PPO run that every policy family shares: processes, resume, the collect/update loop,
validation, checkpoints and logs. A training CLI supplies only its agent (``build_agent``) and
its settings; ``finetune`` (diffusion PPO of a pretrained PDPO policy) and ``train_ppo`` (PPO from
scratch, e.g. CrowdNav++) are thin layers over ``run_ppo``.

One iteration: every process collects ``ppo.n_steps`` steps of its ``num_envs`` envs, then
``ppo.update_epochs`` epochs of minibatch updates (rl/loop.py); validation, checkpoints
(rl/checkpoints.py) and logs (rl/run_log.py) around it.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import draccus
import numpy as np
import torch
from tqdm import tqdm

from .. import fault
from ..checkpoint_files import PRETRAINED_MODEL, SOURCE_PREFIX, TRAIN_CONFIG, TRAINING_STATE
from ..cli import deferred_interrupt
from ..sim.config import PPO_ENV_SEED, PPO_PROCESS_SEEDS, SEED_SPLITS, CrowdSimConfig
from ..sim.envs import CrowdNavVectorEnv
from .agent import ACTOR, CRITIC, check_actor_critic
from .checkpoints import Checkpoints, resume_conflicts
from .config import PPOConfig
from .loop import Collector, update
from .ppo import RunningRewardScaler
from .run_log import RunLog
from .validation import episode_stats, validate

# Files of the source checkpoint carried into every checkpoint (provenance: lerobot-train's
# record); a source written by a PPO run also passes on its run's settings as
# ``source_<config_name>`` (a run that continues another one).
CARRIED_FILES = (TRAIN_CONFIG,)


@dataclass
class TrainingSimConfig(CrowdSimConfig):
    """The simulator in training mode: the intrusion test off (the dynamics and rewards are the
    same, tests/test_orca_robot.py; the ITR/SD metrics are skipped). A class default, not a
    ``default_factory``: draccus builds ``env`` from the field type's defaults as soon as any
    ``--env.*`` is given."""

    # Intrusion test for ITR/SD (5-step ORCA look-ahead of the humans); off in training, for speed.
    compute_intrusion: bool = False


@dataclass
class ValidationConfig:
    # Validate (deterministic sampling) every this many env steps, all processes together; also
    # before the first update and after the last. 0: only then.
    freq: int = 200_000
    # Validation episodes: the first n seeds of the val split (at most its 1,000).
    n_episodes: int = 100


@dataclass
class WandBConfig:
    # Also log to Weights & Biases (TensorBoard event files are always written).
    enable: bool = False
    # offline (no account or network needed; `wandb sync` later), online or disabled.
    mode: str = "offline"
    # W&B project name.
    project: str = "lerobot-crowdnav"


@dataclass
class PPORunConfig:
    """The settings of any PPO run; a CLI adds ``policy`` and its ``ppo`` settings."""

    # Simulator: --env.task, --env.preset and any simulator field, in training mode
    # (--env.compute_intrusion=false unless given).
    env: TrainingSimConfig = field(default_factory=TrainingSimConfig)
    # Envs stepped together by each process.
    num_envs: int = 64
    # Budget in environment steps, all processes together.
    env_steps: int = 12_000_000
    ppo: PPOConfig = field(default_factory=PPOConfig)
    val: ValidationConfig = field(default_factory=ValidationConfig)
    # Write a checkpoint every this many env steps (and at the end).
    save_freq: int = 500_000
    # Seed of the policy's sampling noise, the fresh networks' initialization and the minibatch order.
    seed: int = 1000
    # First train-split episode seed of process 0; process r starts at env_seed + r * 10,000,000
    # (the ORCA demonstrations use seeds from 0; sim/config.py has every block).
    env_seed: int = PPO_ENV_SEED
    # Torch device; default: cuda when available, else cpu.
    device: str | None = None
    # Where checkpoints and logs go (default: outputs/<command>/<task>_<preset>).
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
        if not (lo <= self.env_seed and self.env_seed + world_size * PPO_PROCESS_SEEDS <= hi):
            raise ValueError(f"--env_seed must leave {world_size} blocks of {PPO_PROCESS_SEEDS:,} train seeds below {hi}")
        if self.wandb.mode not in ("offline", "online", "disabled"):
            raise ValueError(f"--wandb.mode must be offline, online or disabled, got {self.wandb.mode!r}")

    def steps_per_iteration(self, world_size: int) -> int:
        return self.ppo.n_steps * self.num_envs * world_size


def crossed(step: int, per_iter: int, freq: int) -> bool:
    """Whether the iteration that ended at ``step`` passed a multiple of ``freq``."""
    return bool(freq) and step // freq > (step - per_iter) // freq


def run_ppo(cfg: PPORunConfig, build_agent: Callable[[Path | None, CrowdSimConfig], torch.nn.Module],
            start_from: Path | None, *, command: str, config_name: str, label: str, done: str) -> dict:
    """One process (rank) of a PPO run; rank 0 also validates, logs and saves the shared parts.

    ``build_agent(source, sim_cfg)``: the actor-critic (rl/agent.py; checked here) on cpu,
    from a pretrained_model directory (``start_from``, or the last checkpoint when resuming) or
    None (``start_from`` was None: a fresh agent, or an error if the CLI needs a source).
    ``config_name``: the run's settings file beside each checkpoint's policy (resume reads it);
    ``command``: the default output directory's parent; ``label``/``done``: progress bar and summary."""
    from accelerate import Accelerator

    # -- set-up: processes, settings, resume source ------------------------------------------------
    device = cfg.device or ("cuda" if torch.cuda.is_available() else "cpu")
    acc = Accelerator(cpu=device == "cpu")
    rank, world, main = acc.process_index, acc.num_processes, acc.is_main_process
    cfg.validate(world)
    sim_cfg = cfg.env.resolve()
    out = Path(cfg.output_dir or f"outputs/{command}/{sim_cfg.task}_{sim_cfg.preset}")
    if acc.device.type == "cpu":  # the cores this process may use (taskset / cgroup), shared by ranks
        torch.set_num_threads(max(1, len(os.sched_getaffinity(0)) // world))
    settings = json.loads(json.dumps(draccus.encode(cfg), default=str))
    ckpts = Checkpoints(out / "checkpoints", acc, max(9, len(str(cfg.env_steps))))
    # --resume=true before the first checkpoint (killed early): start over.
    resumed = cfg.resume and ckpts.last.exists()
    if resumed:
        saved = json.loads((ckpts.last / PRETRAINED_MODEL / config_name).read_text())
        if changed := resume_conflicts(saved, settings, world, defaults=json.loads(json.dumps(
                draccus.encode(type(cfg)()), default=str))):
            raise ValueError(f"--resume=true with different settings than the saved run: {', '.join(changed)}")
        source = ckpts.last / PRETRAINED_MODEL
    else:
        if not cfg.resume and out.exists() and any(out.iterdir()):
            raise FileExistsError(f"{out} exists; pass --resume=true to continue its run or choose another --output_dir")
        source = None if start_from is None else Path(start_from)

    # -- the parts: agent, optimizers, envs, collector -------------------------------------------
    agent = build_agent(source, sim_cfg)
    check_actor_critic(agent, cfg.ppo)
    agent = agent.to(acc.device).eval()  # eval: no dropout, so rollout and update agree
    lrs = {ACTOR: cfg.ppo.actor_lr, CRITIC: cfg.ppo.critic_lr}
    # torch's fused kernel: one pass over a group's tensors instead of a loop (a resumed run keeps
    # the kernel it was saved with: torch restores it with the optimizer's state).
    optimizers = {name: torch.optim.AdamW(params, lr=lrs[name], weight_decay=cfg.ppo.weight_decay, eps=cfg.ppo.adam_eps,
                                          fused=True)
                  for name, params in agent.param_groups().items()}
    model, *opts = acc.prepare(agent, *optimizers.values())
    optimizers = dict(zip(optimizers, opts, strict=True))
    env = CrowdNavVectorEnv(cfg.num_envs, config=sim_cfg)
    scaler = RunningRewardScaler(cfg.num_envs, cfg.ppo.gamma, cfg.ppo.reward_clip) if cfg.ppo.reward_scale_running else None
    collector = Collector(env, agent, scaler, torch.Generator(device=acc.device).manual_seed(cfg.seed * 1000 + rank))
    rng = np.random.default_rng([cfg.seed, rank])  # minibatch order
    # Validation runs the intrusion test (the same dynamics, a few episodes) so the curve shows ITR
    # beside success: the paper's bar is on both.
    val_env = CrowdNavVectorEnv(cfg.val.n_episodes, config=replace(sim_cfg, compute_intrusion=True)) if main else None
    carried = {} if source is None else {name: source / name for name in CARRIED_FILES}
    if source is not None and not resumed:
        carried[SOURCE_PREFIX + config_name] = source / config_name
    elif source is not None:  # resuming: what the run's first source passed on is in the last checkpoint
        carried[SOURCE_PREFIX + config_name] = source / (SOURCE_PREFIX + config_name)
    # wall_s: training wall time so far, summed over resumed invocations (the learning curve's clock).
    progress = {"iteration": 0, "env_steps": 0, "best_val_sr": -1.0, "wall_s": 0.0}

    def save_policy(path: Path) -> None:
        agent.save(path)
        for name, f in carried.items():
            if f.exists():
                (path / name).write_bytes(f.read_bytes())
        (path / config_name).write_text(json.dumps(
            {**settings, "world_size": world, "env_steps_done": progress["env_steps"]}, indent=2))

    def save_rank_state(state: Path, r: int) -> None:
        np.savez(state / f"env_rank{r}.npz", **env.state_dict())
        (state / f"rng_rank{r}.json").write_text(json.dumps(
            {"numpy": rng.bit_generator.state, **collector.state_dict(), "obs_shape": list(collector.obs.shape)}))

    collector.reset(cfg.env_seed + rank * PPO_PROCESS_SEEDS)
    if resumed:
        shared = ckpts.load_shared()
        for name, opt in optimizers.items():
            opt.load_state_dict(shared[f"{name}_opt"])
        progress.update({k: shared.get(k, progress[k]) for k in progress})
        state = ckpts.last / TRAINING_STATE
        with np.load(state / f"env_rank{rank}.npz") as env_state:
            env.load_state_dict(dict(env_state))
        saved_rng = json.loads((state / f"rng_rank{rank}.json").read_text())
        rng.bit_generator.state = saved_rng["numpy"]
        collector.load_state_dict(saved_rng)
    if main:
        ckpts.settle_best(progress["env_steps"])
    log = RunLog(out, main, progress["env_steps"], resumed, cfg.wandb, settings)

    def validate_and_keep_best() -> dict:
        val = validate(agent, val_env, cfg.val.n_episodes, sim_cfg.dt, acc.device)
        if val["val/success_rate"] > progress["best_val_sr"]:
            progress["best_val_sr"] = val["val/success_rate"]
            ckpts.save_best(save_policy, {"env_steps": progress["env_steps"], "iteration": progress["iteration"], **val})
        return val

    # -- the loop -----------------------------------------------------------------------------------
    per_iter = cfg.steps_per_iteration(world)
    # each record names its device: a run moved to a lent GPU and back says which env steps ran where
    device_name = acc.device.type + (f": {torch.cuda.get_device_name(acc.device)}" if acc.device.type == "cuda" else "")
    if progress["iteration"] == 0 and main:
        log.log({"iteration": 0, "env_steps": 0, **validate_and_keep_best()})  # the initial policy
    acc.wait_for_everyone()
    bar = tqdm(total=cfg.env_steps, initial=min(progress["env_steps"], cfg.env_steps), unit="env-step",
               desc=label, disable=not main, dynamic_ncols=True)
    stop = False  # Ctrl-C or SIGTERM: stop after this iteration's checkpoint
    with deferred_interrupt("finishing this iteration and saving a checkpoint") as interrupt:
        while not stop and progress["env_steps"] < cfg.env_steps:
            t0 = time.perf_counter()
            ro = collector.collect(agent, cfg.ppo.n_steps)
            fault.point("ppo.collected")
            t1 = time.perf_counter()
            record = {"iteration": progress["iteration"] + 1, "env_steps": progress["env_steps"] + per_iter,
                      "device": device_name, "rollout_digest": ro.digest(), **episode_stats(ro.episodes, acc)}
            record.update(update(model, agent, ro, cfg.ppo, optimizers, rng, acc,
                                 train_actor=progress["iteration"] >= cfg.ppo.n_critic_warmup_itr))
            t2 = time.perf_counter()
            progress["iteration"] += 1
            progress["env_steps"] += per_iter
            record.update({"perf/rollout_env_steps_per_s": per_iter / (t1 - t0),
                           "perf/update_env_steps_per_s": per_iter / (t2 - t1), "perf/env_steps_per_s": per_iter / (t2 - t0)})
            last = progress["env_steps"] >= cfg.env_steps
            if main and (last or crossed(progress["env_steps"], per_iter, cfg.val.freq)):
                record.update(validate_and_keep_best())
            progress["wall_s"] += time.perf_counter() - t0
            record["time/wall_s"] = progress["wall_s"]
            log.log(record)
            bar.update(min(per_iter, cfg.env_steps - bar.n))
            if main:
                bar.set_postfix({k.split("/")[-1]: f"{record[k]:.3f}" for k in ("train/success_rate", "val/success_rate") if k in record})
            stop = interrupt.requested and not last  # Ctrl-C or SIGTERM in any process: all stop here
            if world > 1:
                stop = bool(acc.reduce(torch.tensor([float(stop)], device=acc.device), reduction="sum").item())
            acc.wait_for_everyone()
            if last or stop or crossed(progress["env_steps"], per_iter, cfg.save_freq):
                ckpts.save(progress["env_steps"], save_policy,
                           {**{f"{name}_opt": opt.state_dict() for name, opt in optimizers.items()}, **progress}, save_rank_state)
    bar.close()
    log.close()
    if stop:
        raise KeyboardInterrupt
    if main:
        procs = "1 process" if world == 1 else f"{world} processes ({acc.distributed_type.value})"
        print(f"\n{done} {progress['env_steps']} env steps on {procs}; "
              f"best validation success rate {progress['best_val_sr']:.3f}; checkpoints in {out / 'checkpoints'}")
    return {"output_dir": str(out), "env_steps": progress["env_steps"], "best_val_success_rate": progress["best_val_sr"]}
