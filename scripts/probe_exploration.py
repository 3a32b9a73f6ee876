"""How much does diffusion PPO's exploration really move the robot? The exploration carry-over probe.

    python scripts/probe_exploration.py --env.task=BoundedCrowdNav-v0 \\
        --policy.path=[BC_CHECKPOINT,OTHER] --output=exploration.json

The fine-tuning rollout explores by sampling each chunk with every denoising std floored at
``--min_sampling_denoising_std`` (0.1, the paper); the env executes the chunk's first action. A
policy that copies its own current velocity (observation entries 7-8: the previous executed action)
copies last step's noise too, so the noise piles up along the episode instead of being redrawn.

Two simulators run each of the first --episodes validation seeds side by side: one driven by the
exploring sampling, one by the deterministic one (DPPO's evaluation sampling). The humans ignore
the robot, so both see the same crowd. At each step t of the exploring episode:

* one-step noise e_t = a_explore(s_t) - a_det(s_t), both at the exploring episode's state: what
  this step's sampling adds;
* path deviation d_t = a_t (exploring episode) - a_t (deterministic episode): how far the
  executed actions are from the noise-free episode's, after t steps of noise.

carry-over = rms(d) / rms(e) over steps [--warmup, --steps) of the pairs still running. It is 1 when
each step's noise is redrawn (a policy that ignores its velocity and whose paths stay close); a
policy that copies a fraction rho of its velocity accumulates an AR(1) walk, 1 / sqrt(1 - rho^2):
about 3 at rho = 0.95. Prints a markdown table; --output writes JSON.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from lerobot_crowdnav.cli import machine_description, run_cli
from lerobot_crowdnav.measure.episodes import json_safe
from lerobot_crowdnav.rl.config import DiffusionPPOConfig
from lerobot_crowdnav.rl.dppo import load_agent
from lerobot_crowdnav.sim.config import SEED_SPLITS, CrowdSimConfig, split_seeds
from lerobot_crowdnav.sim.engine import RUNNING, CrowdSim

sys.path.insert(0, str(Path(__file__).resolve().parent))
from probe_sensitivity import PolicyPaths, merge_paths  # noqa: E402  (the same --policy.path flags)


@dataclass
class ExplorationConfig:
    """The exploration carry-over probe (scripts/probe_exploration.py): rms of the executed actions'
    deviation from the deterministic episode's over rms of one step's sampling noise."""

    # Simulator: --env.task, --env.preset and any simulator field the policies were trained on.
    env: CrowdSimConfig = field(default_factory=CrowdSimConfig)
    # PDPO checkpoints (BC or fine-tuned): --policy.path=DIR, repeated or a list [A,B].
    policy: PolicyPaths = field(default_factory=lambda: PolicyPaths([]))
    # Validation episodes (the first n val seeds), run as one batch.
    episodes: int = 200
    # Steps measured per episode.
    steps: int = 20
    # The first steps left out of the ratio (the deviation starts at 0).
    warmup: int = 5
    # Std floor of the exploring rollout's denoising steps (--ppo.min_sampling_denoising_std).
    min_sampling_denoising_std: float = 0.1
    # Torch seed of the sampling noise.
    seed: int = 0
    # Also write the results as JSON here.
    output: Path | None = None

    def validate(self) -> None:
        size = SEED_SPLITS["val"][1] - SEED_SPLITS["val"][0]
        if not 1 <= self.episodes <= size:
            raise ValueError(f"--episodes must be in [1, {size}] (validation seeds), got {self.episodes}")
        if not 0 <= self.warmup < self.steps:
            raise ValueError(f"need 0 <= --warmup < --steps, got {self.warmup}, {self.steps}")
        if not self.min_sampling_denoising_std > 0:
            raise ValueError("--min_sampling_denoising_std must be > 0")
        if not self.policy.path:
            raise ValueError("--policy.path: give at least one PDPO checkpoint")
        self.env.resolve()


def carry_over(config: CrowdSimConfig, act, episodes: int, steps: int, warmup: int) -> dict:
    """``act(obs (B, D) float32, explore: bool) -> (B, 2)`` m/s actions; the metrics above."""
    seeds = split_seeds("val", episodes)
    explore, det = CrowdSim(config, episodes), CrowdSim(config, episodes)
    explore.reset(seeds), det.reset(seeds)
    both = np.ones(episodes, bool)
    noise, deviation = [], []
    for t in range(steps):
        a_explore = explore.clip_actions(act(explore.obs, True))
        a_here = explore.clip_actions(act(explore.obs, False))
        a_det = det.clip_actions(act(det.obs, False))
        if t >= warmup:
            noise.append((a_explore - a_here)[both])
            deviation.append((a_explore - a_det)[both])
        both &= (explore.step(a_explore).event == RUNNING) & (det.step(a_det).event == RUNNING)
        if not both.any():
            break
    if not noise or not sum(len(n) for n in noise):
        raise ValueError(f"no pair of episodes ran past step {warmup}")
    rms = {name: float(np.sqrt(np.mean(np.concatenate(x) ** 2) * 2)) for name, x in (("noise", noise), ("deviation", deviation))}
    per_step = [float(np.sqrt(np.mean(d**2) * 2)) if len(d) else float("nan") for d in deviation]
    return {"pairs_steps": int(sum(len(n) for n in noise)), "rms_noise": rms["noise"], "rms_deviation": rms["deviation"],
            "carry_over": rms["deviation"] / rms["noise"], "rms_deviation_per_step": per_step}


def pdpo_act(path: str, cfg: ExplorationConfig, config: CrowdSimConfig):
    """A PDPO checkpoint's fine-tuning sampling as an ``act``; explore and not share the noise stream."""
    agent = load_agent(Path(path), DiffusionPPOConfig(min_sampling_denoising_std=cfg.min_sampling_denoising_std), cfg.seed).eval()
    generator = torch.Generator().manual_seed(cfg.seed)

    def act(obs: np.ndarray, explore: bool) -> np.ndarray:
        return agent.act(torch.as_tensor(obs), None, explore, generator).action.numpy().astype(np.float64)

    return act


def run(cfg: ExplorationConfig) -> dict:
    cfg.validate()
    config = dataclasses.replace(cfg.env, compute_intrusion=False).resolve()
    results = {}
    for path in tqdm(cfg.policy.path, desc="exploration probe", unit="policy"):
        results[path] = carry_over(config, pdpo_act(path, cfg, config), cfg.episodes, cfg.steps, cfg.warmup)
    print(f"\n{config.task} ({config.preset}), {cfg.episodes} val episode pairs, steps {cfg.warmup}-{cfg.steps - 1}, "
          f"sampling std floor {cfg.min_sampling_denoising_std}\n")
    print("| policy | rms one-step noise (m/s) | rms path deviation (m/s) | carry-over |\n|---|---|---|---|")
    for name, r in results.items():
        print(f"| {name} | {r['rms_noise']:.3f} | {r['rms_deviation']:.3f} | {r['carry_over']:.2f} |")
    summary = {"env": config.to_dict(), "episodes": cfg.episodes, "steps": cfg.steps, "warmup": cfg.warmup,
               "min_sampling_denoising_std": cfg.min_sampling_denoising_std, "seed": cfg.seed,
               "machine": machine_description(), "policies": results}
    if cfg.output:
        cfg.output.parent.mkdir(parents=True, exist_ok=True)
        cfg.output.write_text(json.dumps(json_safe(summary), indent=2))
    return summary


def main(argv: list[str] | None = None) -> None:
    run_cli(ExplorationConfig, run, merge_paths(sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    main()
