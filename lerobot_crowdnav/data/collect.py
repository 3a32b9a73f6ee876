"""Collect ORCA demonstrations: ``python datasets_scripts/collect_orca.py --episodes 3000``.

The built-in ORCA robot drives the batched simulator on consecutive train seeds (``--seed``,
``--seed + 1``, ...), a block of ``--batch_size`` episodes at a time; the dataset holds the first
``--episodes`` episodes of that stream that ``--keep`` accepts, in seed order. So an interrupted
run resumed with ``--resume`` ends with exactly the dataset an uninterrupted one writes.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .. import fault
from ..cli import run_cli
from ..sim.config import SEED_SPLITS, CrowdSimConfig
from .dataset import DemonstrationWriter, outcome_counts
from .hub import dataset_card, push_dataset_to_dir, split_repo_id
from ..sim.engine import EVENT_NAMES, RUNNING, SUCCESS, CrowdSim

KEEP = ("all", "success")


@dataclass
class CollectConfig:
    # Number of episodes written to the dataset.
    episodes: int = 3000
    # Simulator: --env.task (default BoundedCrowdNav-v0), --env.preset, any simulator field. The
    # intrusion look-ahead is skipped (it does not change trajectories).
    env: CrowdSimConfig = field(default_factory=CrowdSimConfig)
    # First train seed; the run walks seed, seed + 1, ... until enough episodes are kept.
    seed: int = 0
    # Dataset name, <org>/<name>.
    repo_id: str = "local/crowdnav_orca"
    # Dataset directory (default: outputs/datasets/<repo_id>).
    root: Path | None = None
    # Episodes kept: success (successful episodes only; the default, measured to pretrain the
    # better policy, see docs/dataset.md) or all (every outcome).
    keep: str = "success"
    # Complete an interrupted collection in root to --episodes, with the same seeds (an empty or
    # missing root: collect from scratch).
    resume: bool = False
    # Delete an existing root and collect from scratch.
    overwrite: bool = False
    # Also write the Hub repository layout to <dir>/datasets/<org>/<name>/.
    push_to_hub_dir: Path | None = None
    # Replace an existing <dir>/datasets/<org>/<name>/.
    push_overwrite: bool = False
    # Upload with lerobot's own push_to_hub (needs a token and network).
    push_to_hub: bool = False
    # Episodes simulated and committed together (one data file each).
    batch_size: int = 256

    def validate(self) -> Path:
        if self.episodes < 1:
            raise ValueError(f"--episodes must be >= 1, got {self.episodes}")
        if self.keep not in KEEP:
            raise ValueError(f"--keep must be one of {', '.join(KEEP)}, got {self.keep!r}")
        if self.batch_size < 1:
            raise ValueError(f"--batch_size must be >= 1, got {self.batch_size}")
        lo, hi = SEED_SPLITS["train"]
        if not lo <= self.seed < hi:
            raise ValueError(f"--seed must be a train seed in [{lo}, {hi}), got {self.seed}")
        split_repo_id(self.repo_id)
        if self.resume and self.overwrite:
            raise ValueError("--resume and --overwrite exclude each other")
        root = Path(self.root or Path("outputs/datasets") / self.repo_id)
        if root.exists() and any(root.iterdir()) and not (self.resume or self.overwrite):
            raise FileExistsError(f"{root} exists and is not empty: pass --resume=true to complete it, "
                                  "--overwrite=true to replace it, or another --root")
        if self.resume and root.exists() and any(root.iterdir()) and not (root / "meta/info.json").exists():
            raise FileNotFoundError(f"--resume: {root} holds no dataset to resume")
        self.env.resolve()
        return root


def rollout_block(sim: CrowdSim, seeds: np.ndarray) -> list[dict]:
    """One ORCA episode per slot for ``seeds``; returns them in seed order, each with its
    pre-step observations, executed (clipped) actions, rewards, event and success."""
    b = len(seeds)
    slots = np.arange(sim.num_envs)
    padded = np.concatenate([seeds, np.full(sim.num_envs - b, seeds[0])])  # idle slots if short
    sim.reset(padded, slots)
    t_max = sim.config.max_steps
    obs = np.empty((t_max, sim.num_envs, sim.config.obs_dim), np.float32)
    act = np.empty((t_max, sim.num_envs, 2), np.float32)
    rew = np.empty((t_max, sim.num_envs), np.float32)
    end = np.full(sim.num_envs, -1)  # episode length once ended; idle slots never run
    end[b:] = 0
    event = np.zeros(sim.num_envs, np.int64)
    for t in range(t_max):
        running = end < 0  # ended slots are not simulated further
        if not running.any():
            break
        obs[t] = sim.obs
        a = sim.clip_actions(sim.orca_actions(running))
        res = sim.step(a, running)
        act[t] = a
        rew[t] = res.reward
        new = running & (res.event != RUNNING)
        end[new] = t + 1
        event[new] = res.event[new]
    return [{"seed": int(seeds[i]), "event": EVENT_NAMES[event[i]], "success": bool(event[i] == SUCCESS),
             "obs": obs[: end[i], i], "action": act[: end[i], i], "reward": rew[: end[i], i]}
            for i in range(b)]


def collect(cfg: CollectConfig) -> dict:
    root = cfg.validate()
    sim_cfg = dataclasses.replace(cfg.env, compute_intrusion=False).resolve()
    collection = {"repo_id": cfg.repo_id, "seed": cfg.seed, "keep": cfg.keep, "policy": "orca",
                  "demonstrator": sim_cfg.orca_description,
                  "env": sim_cfg.to_dict(), "episodes": cfg.episodes}
    if cfg.overwrite and root.exists():
        shutil.rmtree(root)
    writer = DemonstrationWriter(root, cfg.repo_id, sim_cfg, collection, resume=cfg.resume)
    done = [row for block in writer.committed_blocks() for row in block]
    kept = len(done)
    next_seed = done[-1]["seed"] + 1 if done else cfg.seed
    sim = CrowdSim(sim_cfg, min(cfg.batch_size, cfg.episodes))  # the same blocks as an uninterrupted run
    start = time.perf_counter()
    frames = 0
    bar = tqdm(total=cfg.episodes, initial=min(kept, cfg.episodes), unit="ep", desc="collect orca")
    while kept < cfg.episodes:
        if next_seed + sim.num_envs > SEED_SPLITS["train"][1]:
            raise RuntimeError("ran out of train seeds")
        seeds = np.arange(next_seed, next_seed + sim.num_envs)
        next_seed += sim.num_envs
        episodes = rollout_block(sim, seeds)
        if cfg.keep == "success":
            episodes = [e for e in episodes if e["success"]]
        episodes = episodes[: cfg.episodes - kept]
        writer.append(episodes)
        kept += len(episodes)
        frames += sum(len(e["action"]) for e in episodes)
        bar.update(len(episodes))
        bar.set_postfix(frames=frames, eps_per_s=f"{(kept - len(done)) / (time.perf_counter() - start):.0f}")
    bar.close()
    elapsed = time.perf_counter() - start

    rows = [row for block in writer.committed_blocks() for row in block][: cfg.episodes]
    counts = outcome_counts([r["event"] for r in rows])
    summary = {"root": str(root), "episodes": len(rows), "frames": writer.info.total_frames,
               "outcomes": counts, "first_seed": rows[0]["seed"], "last_seed": rows[-1]["seed"],
               "wall_time_s": elapsed}
    # The card comes last and marks the dataset complete (the main job's test for it).
    fault.write_text(root / "README.md", str(dataset_card(cfg.repo_id, writer.info, sim_cfg, collection, summary)))
    summary["size_mb"] = _size_mb(root)
    if cfg.push_to_hub_dir:
        summary["hub_dir"] = str(push_dataset_to_dir(root, cfg.repo_id, cfg.push_to_hub_dir,
                                                     overwrite=cfg.push_overwrite))
    if cfg.push_to_hub:
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        LeRobotDataset(cfg.repo_id, root=root).push_to_hub(tags=["crowd-navigation", "lerobot-crowdnav"])
    print(json.dumps(summary, indent=2))
    return summary


def _size_mb(root: Path) -> float:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file()) / 2**20


def main(argv: list[str] | None = None) -> None:
    run_cli(CollectConfig, collect, argv, "the committed episodes are saved; rerun with --resume=true to complete")


if __name__ == "__main__":
    main()
