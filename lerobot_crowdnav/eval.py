"""Evaluate a robot policy on fixed episode seeds: ``lerobot-crowdnav-eval``.

    lerobot-crowdnav-eval --policy.type=orca --env.task=BoundedCrowdNav-v0 \\
        --eval.n_episodes=500 --eval.split=test --output_dir=outputs/eval/orca

Prints the markdown row ``SR | NT | PL | ITR | SD`` (+ CR, TR, OOB for the original variant) and
writes ``<output_dir>/metrics.json``: the metrics (``sr, cr, tr, nt, pl, itr, sd, oob``; rates as
fractions, seconds, metres), ``n_episodes``, the resolved env config and one record per episode.
"""

from __future__ import annotations

import json
import math
import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np
from tqdm import tqdm

from .config import SEED_SPLITS, CrowdSimConfig, split_seeds
from .envs import CrowdNavEnv, CrowdNavVectorEnv
from .metrics import EpisodeRecord, compute_metrics, markdown_header, markdown_row


@dataclass
class RobotPolicyConfig(draccus.ChoiceRegistry):
    """The robot policy to evaluate (``--policy.type=...``)."""

    @property
    def name(self) -> str:
        return self.get_choice_name(self.__class__)


@RobotPolicyConfig.register_subclass("orca")
@dataclass
class OrcaPolicyConfig(RobotPolicyConfig):
    """The ORCA robot (CrowdNav++'s baseline and the demonstrator): sees the humans it has
    observed, assumes they reciprocate, and avoids the walls in the bounded variant."""


@RobotPolicyConfig.register_subclass("straight")
@dataclass
class StraightPolicyConfig(RobotPolicyConfig):
    """Full speed toward the goal, ignoring humans: a floor for learned policies."""


@dataclass
class EvalSettings:
    # Number of episodes: the first n seeds of the split.
    n_episodes: int = 500
    # Seed split: test (500 seeds, every reported table), val (100, checkpoint selection), train.
    split: str = "test"
    # Environments stepped together in one batch (at most n_episodes).
    batch_size: int = 256
    # Also save this many episodes (the first seeds) as GIFs under output_dir/videos.
    n_videos: int = 0

    def validate(self) -> None:
        if self.split not in SEED_SPLITS:
            raise ValueError(f"--eval.split must be one of {', '.join(SEED_SPLITS)}, got {self.split!r}")
        size = SEED_SPLITS[self.split][1] - SEED_SPLITS[self.split][0]
        if not 1 <= self.n_episodes <= size:
            raise ValueError(f"--eval.n_episodes must be in [1, {size}] for split {self.split!r}, got {self.n_episodes}")
        if self.batch_size < 1:
            raise ValueError(f"--eval.batch_size must be >= 1, got {self.batch_size}")
        if self.n_videos < 0:
            raise ValueError(f"--eval.n_videos must be >= 0, got {self.n_videos}")


@dataclass
class EvalConfig:
    # Simulator: --env.task (CrowdNav-v0 | BoundedCrowdNav-v0), --env.preset (paper | crowdnavpp)
    # and any simulator field, e.g. --env.randomize_attributes=false.
    env: CrowdSimConfig = field(default_factory=CrowdSimConfig)
    # Robot policy: --policy.type=orca | straight.
    policy: RobotPolicyConfig = field(default_factory=OrcaPolicyConfig)
    eval: EvalSettings = field(default_factory=EvalSettings)
    # Where metrics.json goes (default: outputs/eval/<task>_<preset>_<policy>_<split>).
    output_dir: Path | None = None
    # Replace the results of an existing output_dir instead of refusing to run.
    overwrite: bool = False


def run_episodes(env: CrowdNavVectorEnv, policy: str, split: str, n_episodes: int,
                 progress: bool = True) -> list[EpisodeRecord]:
    """Run the first ``n_episodes`` seeds of ``split`` with a built-in policy; records by seed."""
    seeds = split_seeds(split, n_episodes)
    wanted = set(seeds)
    env.reset(seed=seeds[0])
    records: dict[int, EpisodeRecord] = {}
    bar = tqdm(total=n_episodes, desc=f"eval {policy}", unit="ep", disable=not progress)
    while len(records) < n_episodes:
        _, _, _, _, info = env.step(env.expert_actions(policy))
        if "final_info" in info:
            for b in np.flatnonzero(info["_final_info"]):
                rec = EpisodeRecord.from_final_info(info["final_info"], b)
                if rec.seed in wanted and rec.seed not in records:
                    records[rec.seed] = rec
                    bar.update(1)
            bar.set_postfix(sr=f"{np.mean([r.event == 'success' for r in records.values()]):.3f}")
    bar.close()
    return [records[s] for s in seeds]


def _json_safe(value):
    """Strict JSON: undefined means (NaN, e.g. NT without a success) become null."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def machine_description() -> str:
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            model = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{model}, {os.cpu_count()} logical cores"


def evaluate(cfg: EvalConfig) -> dict:
    cfg.eval.validate()
    sim_cfg = cfg.env.resolve()
    policy = cfg.policy.name
    out = cfg.output_dir or Path("outputs/eval") / f"{sim_cfg.task}_{sim_cfg.preset}_{policy}_{cfg.eval.split}"
    out = Path(out)
    metrics_path = out / "metrics.json"
    if metrics_path.exists() and not cfg.overwrite:
        raise FileExistsError(f"{metrics_path} exists; pass --overwrite=true to replace it or choose another --output_dir")
    batch = min(cfg.eval.batch_size, cfg.eval.n_episodes)
    env = CrowdNavVectorEnv(batch, config=sim_cfg)
    start = time.perf_counter()
    records = run_episodes(env, policy, cfg.eval.split, cfg.eval.n_episodes)
    elapsed = time.perf_counter() - start
    metrics = compute_metrics(records, sim_cfg.dt)
    result = {
        **metrics,
        "n_episodes": len(records),
        "split": cfg.eval.split,
        "policy": policy,
        "env": sim_cfg.to_dict(),
        "markdown": markdown_row(metrics, sim_cfg.bounded),
        "wall_time_s": elapsed,
        "machine": machine_description(),
        "episodes": [r.to_dict() for r in records],
    }
    out.mkdir(parents=True, exist_ok=True)
    tmp = metrics_path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(_json_safe(result), indent=2, allow_nan=False))
    tmp.replace(metrics_path)
    if cfg.eval.n_videos:
        from .render import record_episode

        single = CrowdNavEnv(render_mode="rgb_array", config=sim_cfg)
        for seed in split_seeds(cfg.eval.split, min(cfg.eval.n_videos, cfg.eval.n_episodes)):
            record_episode(single, out / "videos" / f"{policy}_seed{seed}.gif", seed, policy)
    print(f"\n{sim_cfg.task} ({sim_cfg.preset}), policy {policy}, {len(records)} {cfg.eval.split} episodes:")
    print(markdown_header(sim_cfg.bounded))
    print(result["markdown"])
    print(f"wrote {metrics_path}")
    return result


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=EvalConfig, args=argv)
    try:
        evaluate(cfg)
    except (ValueError, FileExistsError) as e:
        raise SystemExit(f"error: {e}") from None


if __name__ == "__main__":
    main()
