"""Collect ORCA demonstrations: ``python datasets_scripts/collect_orca.py --episodes 3000``.

The built-in ORCA robot drives the batched simulator on consecutive train seeds (``--seed``,
``--seed + 1``, ...), a block of ``--batch_size`` episodes at a time; the dataset holds the first
``--episodes`` episodes of that stream that ``--keep`` accepts, in seed order. So an interrupted
run resumed with ``--resume`` ends with exactly the dataset an uninterrupted one writes. A dataset
that DAgger rounds were aggregated into takes no more demonstrations.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
from lerobot.datasets.io_utils import load_info
from tqdm import tqdm

from .. import fault
from ..cli import run_cli
from ..sim.config import DAGGER_SEED_BASE, SEED_SPLITS, CrowdSimConfig
from .dataset import CARD_FILE, COLLECTION_FILE, DemonstrationWriter, committed_episodes_files, outcome_counts
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
    # missing root: collect from scratch; refused once DAgger rounds were aggregated into it).
    resume: bool = False
    # Delete an existing root (a LeRobotDataset or an empty directory) and collect from scratch.
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
        if root.exists() and not root.is_dir():
            raise FileExistsError(f"--root={root} is a file, not a dataset directory: pass a directory")
        filled = root.exists() and any(root.iterdir())
        if filled and not (self.resume or self.overwrite):
            raise FileExistsError(f"{root} exists and is not empty: pass --resume=true to complete it, "
                                  "--overwrite=true to replace it, or another --root")
        if self.resume and filled and not (root / "meta/info.json").exists():
            raise FileNotFoundError(f"--resume: {root} holds no dataset to resume")
        if self.overwrite and filled and not (root / "meta/info.json").exists():
            raise FileExistsError(f"--overwrite: {root} is not a LeRobotDataset (no meta/info.json) and is left as "
                                  "it is: check --root, or delete it yourself")
        if self.resume and (root / COLLECTION_FILE).exists() and holds_dagger_rounds(root):
            raise ValueError(f"--resume: DAgger rounds were aggregated into {root}, and demonstrations cannot follow "
                             "them (they would be drawn from the learners' seeds and the card would lose the rounds); "
                             "collect the demonstrations you need into a new --root, then run the DAgger rounds on it again")
        self.env.resolve()
        return root


def demonstration_env(env: CrowdSimConfig) -> CrowdSimConfig:
    """The simulator the demonstrations are collected in (its ``to_dict()`` is the collection
    record's ``env``): ``env`` without the intrusion look-ahead, which changes no trajectory."""
    return dataclasses.replace(env, compute_intrusion=False).resolve()


def holds_dagger_rounds(root: Path) -> bool:
    """Whether DAgger rounds were aggregated into the collection at ``root``: recorded ones, or one
    committed and killed before its record (episodes from the learners' seed blocks, which the
    demonstrations, walking up from a seed below them, do not reach)."""
    collection = json.loads((root / COLLECTION_FILE).read_text())
    if collection.get("dagger"):
        return True
    if collection["seed"] >= DAGGER_SEED_BASE:
        return False
    return any(pq.read_table(f, columns=["seed"]).column("seed").to_numpy().max() >= DAGGER_SEED_BASE
               for f in committed_episodes_files(root, load_info(root)))


def orca_episodes(sim: CrowdSim, first_seed: int) -> Iterator[dict]:
    """ORCA episodes on the consecutive train seeds from ``first_seed``, yielded in seed order,
    each with its pre-step observations, executed (clipped) actions, rewards, event and success.

    A slot whose episode ends starts the next seed in the same step, so every step simulates a
    full batch instead of waiting for the longest episode of a block (a seed's episode does not
    depend on its slot, so the episodes are those of any other schedule)."""
    b, t_max = sim.num_envs, sim.config.max_steps
    obs = np.empty((b, t_max, sim.config.obs_dim), np.float32)
    act = np.empty((b, t_max, 2), np.float32)
    rew = np.empty((b, t_max), np.float32)
    slots, t = np.arange(b), np.zeros(b, np.int64)
    seeds = np.arange(first_seed, first_seed + b)
    next_seed, emit = first_seed + b, first_seed
    sim.reset(seeds)
    finished: dict[int, dict] = {}
    while True:
        obs[slots, t] = sim.obs
        a = sim.clip_actions(sim.orca_actions())
        res = sim.step(a)
        act[slots, t], rew[slots, t] = a, res.reward
        t += 1
        ended = np.flatnonzero(res.event != RUNNING)
        for i in ended:
            n, event = t[i], res.event[i]
            finished[int(seeds[i])] = {"seed": int(seeds[i]), "event": EVENT_NAMES[event], "success": bool(event == SUCCESS),
                                       "obs": obs[i, :n].copy(), "action": act[i, :n].copy(), "reward": rew[i, :n].copy()}
        if len(ended):
            if next_seed + len(ended) > SEED_SPLITS["train"][1]:
                raise RuntimeError("ran out of train seeds")
            seeds[ended] = np.arange(next_seed, next_seed + len(ended))
            next_seed += len(ended)
            t[ended] = 0
            sim.reset(seeds[ended], ended)
        while emit in finished:
            yield finished.pop(emit)
            emit += 1


def collect(cfg: CollectConfig) -> dict:
    root = cfg.validate()
    sim_cfg = demonstration_env(cfg.env)
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
    stream = orca_episodes(sim, next_seed)
    while kept < cfg.episodes:
        # Blocks of batch_size consecutive seeds, committed together (what a resume restarts from).
        episodes = [next(stream) for _ in range(sim.num_envs)]
        if cfg.keep == "success":
            episodes = [e for e in episodes if e["success"]]
        episodes = episodes[: cfg.episodes - kept]
        writer.append(episodes)
        kept += len(episodes)
        frames += sum(len(e["action"]) for e in episodes)
        bar.update(len(episodes))
        bar.set_postfix(frames=frames, eps_per_s=f"{(kept - len(done)) / (time.perf_counter() - start):.0f}")
    stream.close()
    bar.close()
    elapsed = time.perf_counter() - start

    rows = [row for block in writer.committed_blocks() for row in block]  # a resume may find more than --episodes
    counts = outcome_counts([r["event"] for r in rows])
    summary = {"root": str(root), "episodes": len(rows), "frames": writer.info.total_frames,
               "outcomes": counts, "first_seed": rows[0]["seed"], "last_seed": rows[-1]["seed"],
               "wall_time_s": elapsed, "resumed_after": len(done)}
    # The card comes last and marks the dataset complete (the main job's test for it).
    fault.write_text(root / CARD_FILE, str(dataset_card(cfg.repo_id, writer.info, sim_cfg, collection, summary)))
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
