"""Simulator throughput: ``lerobot-crowdnav-bench`` (also ``python -m lerobot_crowdnav.sim.benchmark``).

Measures env-steps/s (one env-step = one environment advanced by dt) through the public APIs:
the native batched env (``CrowdNavVectorEnv``, autoreset and info included) for each batch size
with random actions (training mode: no intrusion look-ahead), random actions with the intrusion
metrics, and the built-in ORCA robot; and the single-env gymnasium API (``gym.make`` + ``step``)
with random actions and in test mode (ORCA robot, intrusion metrics on). The other crowd models
(``--crowds``: reactive ORCA humans, social-force humans, both; docs/simulator.md, "Crowd
models") add rows with random actions and with the ORCA robot, each with its cost per env-step
relative to the benchmark's own crowd (``orca``) at the same batch size and actions: the crowds'
runs interleaved, the median of the per-repeat ratios. Each figure is the median of ``--repeats``
timed runs after a warm-up.
"""

from __future__ import annotations

import json
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np

from ..cli import machine_description, run_cli
from .config import CROWDS, CrowdSimConfig
from .envs import CrowdNavVectorEnv


@dataclass
class BenchmarkConfig:
    # Variant benchmarked: CrowdNav-v0 or BoundedCrowdNav-v0.
    task: str = "BoundedCrowdNav-v0"
    # Simulator preset: paper or crowdnavpp.
    preset: str = "paper"
    # Batch sizes of the native batched env.
    batch_sizes: list[int] = field(default_factory=lambda: [1, 64, 1024])
    # Timed runs per figure; the median is reported.
    repeats: int = 5
    # Env-steps per timed run (divided among the batch), roughly.
    steps_per_run: int = 100_000
    # Crowd models timed besides the benchmark's own (orca): any of reactive_orca, social_force,
    # reactive_social_force (random actions and the ORCA robot at every batch size).
    crowds: list[str] = field(default_factory=lambda: ["reactive_orca", "social_force", "reactive_social_force"])
    # Also write the table and raw timings as JSON here.
    output: Path | None = None


def _time_vector(cfg: BenchmarkConfig, batch: int, mode: str, seed: int, crowd: str = "orca") -> float:
    intrusion = mode == "random + intrusion"
    env = CrowdNavVectorEnv(batch, robot_policy="orca" if mode == "orca robot" else None,
                            config=CrowdSimConfig(task=cfg.task, preset=cfg.preset,
                                                  compute_intrusion=intrusion, **CROWDS[crowd]))
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    steps = max(20, cfg.steps_per_run // batch // (4 if intrusion else 1))
    actions = rng.uniform(-1, 1, size=(steps, batch, 2))
    for t in range(5):  # warm-up (compilation is cached on disk after the first run)
        env.step(actions[t])
    start = time.perf_counter()
    for t in range(steps):
        env.step(actions[t])
    return steps * batch / (time.perf_counter() - start)


def _time_single(cfg: BenchmarkConfig, mode: str, seed: int) -> float:
    """``mode``: "random" (training mode) or "orca robot + intrusion" (test mode, the setting
    of CrowdNav++'s own ORCA evaluation)."""
    test_mode = mode != "random"
    env = gym.make(f"lerobot_crowdnav/{cfg.task}", preset=cfg.preset, compute_intrusion=test_mode)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    steps = max(200, cfg.steps_per_run // 20 // (3 if test_mode else 1))
    actions = rng.uniform(-1, 1, size=(steps, 2))
    start = time.perf_counter()
    for t in range(steps):
        action = env.unwrapped.expert_action("orca") if test_mode else actions[t]
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    return steps / (time.perf_counter() - start)


def run(cfg: BenchmarkConfig) -> dict:
    if cfg.repeats < 1 or cfg.steps_per_run < 1 or any(b < 1 for b in cfg.batch_sizes):
        raise ValueError("repeats, steps_per_run and batch sizes must be >= 1")
    unknown = [c for c in cfg.crowds if c not in CROWDS or c == "orca"]
    if unknown:
        raise ValueError(f"unknown crowds {unknown}; choose from {', '.join(c for c in CROWDS if c != 'orca')}")
    CrowdSimConfig(task=cfg.task, preset=cfg.preset).resolve()
    rows = []
    for batch in cfg.batch_sizes:
        for mode in ("random", "random + intrusion", "orca robot"):
            crowds = ["orca", *cfg.crowds] if mode != "random + intrusion" else ["orca"]
            runs = {crowd: [] for crowd in crowds}
            for r in range(cfg.repeats):  # crowds interleaved: their ratios see the same machine load
                for crowd in crowds:
                    runs[crowd].append(_time_vector(cfg, batch, mode, seed=r, crowd=crowd))
            for crowd, rates in runs.items():
                rate = statistics.median(rates)
                # Paired by repeat (the runs beside each other saw the same load), then the median.
                cost = statistics.median(b / r for b, r in zip(runs["orca"], rates))
                rows.append({"api": "CrowdNavVectorEnv", "batch": batch, "mode": mode, "crowd": crowd,
                             "median_steps_per_s": rate, "runs": rates, "cost_vs_orca": cost})
                print(f"B={batch:5d} {mode:20s} {crowd:22s} {rate:12,.0f} env-steps/s "
                      f"({cost:.2f}x the cost of orca)", flush=True)
    for mode in ("random", "orca robot + intrusion"):
        rates = [_time_single(cfg, mode, seed=r) for r in range(cfg.repeats)]
        rows.append({"api": "gym.make (single env)", "batch": 1, "mode": mode, "crowd": "orca",
                     "median_steps_per_s": statistics.median(rates), "runs": rates})
        print(f"single env   {mode:20s} {'orca':22s} {statistics.median(rates):12,.0f} env-steps/s", flush=True)
    lines = ["| API | B | actions | crowd | env-steps/s (median) | cost per env-step vs orca |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['api']} | {r['batch']} | {r['mode']} | {r['crowd']} | {r['median_steps_per_s']:,.0f} | "
              + (f"{r['cost_vs_orca']:.2f}x |" if "cost_vs_orca" in r else "- |") for r in rows]
    table = "\n".join(lines)
    result = {"machine": machine_description(), "task": cfg.task, "preset": cfg.preset,
              "repeats": cfg.repeats, "rows": rows, "markdown": table}
    print(f"\n{cfg.task} ({cfg.preset}) on {result['machine']}, median of {cfg.repeats} runs:\n{table}")
    if cfg.output:
        cfg.output.parent.mkdir(parents=True, exist_ok=True)
        cfg.output.write_text(json.dumps(result, indent=2))
    return result


def main(argv: list[str] | None = None) -> None:
    run_cli(BenchmarkConfig, run, argv)


if __name__ == "__main__":
    main()
