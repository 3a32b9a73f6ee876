"""Evaluate a robot policy on fixed episode seeds: ``lerobot-crowdnav-eval``.

    lerobot-crowdnav-eval --policy.type=orca --env.task=BoundedCrowdNav-v0 \\
        --eval.n_episodes=500 --eval.split=test --output_dir=outputs/eval/orca
    lerobot-crowdnav-eval --policy.path=outputs/train/<run>/checkpoints/last/pretrained_model

Prints the markdown row ``SR | NT | PL | ITR | SD`` (+ CR, TR, OOB for the original variant) and
writes ``<output_dir>/metrics.json``: the metrics (``sr, cr, tr, nt, pl, itr, sd, oob``; rates as
fractions, seconds, metres), ``n_episodes``, the resolved env config, the ``request`` it answers
(:func:`request`: what the main job and the baselines compare before reusing it) and one record
per episode.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np

from ..checkpoint_files import PRETRAINED_MODEL
from ..cli import machine_description, run_cli
from ..measure.episodes import LearnedPolicy, json_safe, run_episodes
from ..measure.metrics import METRICS_VERSION, compute_metrics, markdown_header, markdown_row
from ..sim.config import SEED_SPLITS, CrowdSimConfig, split_seeds
from ..sim.engine import SIM_VERSION
from ..sim.envs import CrowdNavEnv, CrowdNavVectorEnv


@dataclass
class RobotPolicyConfig(draccus.ChoiceRegistry):
    """The robot policy to evaluate (``--policy.type=...``)."""

    @property
    def name(self) -> str:
        return self.get_choice_name(self.__class__)


@RobotPolicyConfig.register_subclass("orca")
@dataclass
class OrcaPolicyConfig(RobotPolicyConfig):
    """The ORCA robot (CrowdNav++'s baseline and the demonstrator), one of CrowdNav++'s two, chosen
    by --env.orca_robot: look_ahead (paper preset default; CrowdSimPred: every visible human now and
    1..5 steps ahead on its true ORCA path, so it keeps clear of where people will be) or
    current_state (crowdnavpp default; CrowdSimVarNum: each human where last seen, extrapolated
    while out of sight). It ignores the Bounded walls like CrowdNav++'s robot unless
    --env.orca_robot_wall_aware=true."""


@RobotPolicyConfig.register_subclass("straight")
@dataclass
class StraightPolicyConfig(RobotPolicyConfig):
    """Full speed toward the goal, ignoring humans: a floor for learned policies."""


@RobotPolicyConfig.register_subclass("pretrained")
@dataclass
class PretrainedPolicyConfig(RobotPolicyConfig):
    """A trained lerobot policy checkpoint (PDPO or any lerobot policy on observation.state):
    --policy.path=<output_dir>/checkpoints/<step>/pretrained_model (or a hub-format directory)."""

    # Checkpoint directory holding config.json, model.safetensors and the processors.
    path: Path | None = None
    # Torch device for the policy.
    device: str = "cpu"
    # Seed of the policy's sampling noise.
    seed: int = 0
    # PDPO only: true keeps the checkpoint's own choice (config.json's use_ema); false samples with
    # the raw trained weights instead of their EMA (an ablation).
    use_ema: bool = True
    # PDPO only: sample with DDIM over this many steps (0: DDPM over all K) instead of the
    # checkpoint's own sampler; a fine-tuned policy only runs the sampler it was fine-tuned with.
    ddim_steps: int | None = None

    @property
    def name(self) -> str:
        path = Path(self.path or "?")
        if path.name == PRETRAINED_MODEL and len(path.parents) >= 3:  # <run>/checkpoints/<step>/
            return f"{path.parents[2].name}@{path.parent.name}"
        return path.name


@dataclass
class EvalSettings:
    # Number of episodes: the first n seeds of the split.
    n_episodes: int = 500
    # Seed split: test (500 seeds, every reported table), val (1,000, checkpoint and recipe selection),
    # holdout (10,000 never used to choose or report: does a result hold on fresh episodes?), train.
    split: str = "test"
    # Environments stepped together in one batch (at most n_episodes).
    batch_size: int = 256
    # Also save this many episodes (the first seeds) as GIFs under output_dir/videos.
    n_videos: int = 0

    @property
    def num_envs(self) -> int:
        """The environments stepped together: the batch size, capped at the episode count."""
        return min(self.batch_size, self.n_episodes)

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
    # Robot policy: --policy.type=orca (the ORCA robot) | straight (full speed to the goal) |
    # pretrained (a trained checkpoint; --policy.path=<checkpoint> alone implies it).
    policy: RobotPolicyConfig = field(default_factory=OrcaPolicyConfig)
    eval: EvalSettings = field(default_factory=EvalSettings)
    # Where metrics.json goes (default: outputs/eval/<task>_<preset>_<policy>_<split>).
    output_dir: Path | None = None
    # Replace the results of an existing output_dir instead of refusing to run.
    overwrite: bool = False


def request(cfg: EvalConfig) -> dict:
    """What decides an evaluation's numbers (saved in metrics.json): the policy and its settings,
    the resolved simulator and its episodes' version, the split, the episode count and the metric
    definitions; for a trained policy also the batch size, since its sampling noise is drawn for
    the whole batch at once (the ORCA and straight robots give the same episodes at any)."""
    asked = {"metrics_version": METRICS_VERSION, "sim_version": SIM_VERSION,
             "policy": {"type": cfg.policy.name, **draccus.encode(cfg.policy)},
             "env": cfg.env.resolve().to_dict(), "split": cfg.eval.split, "n_episodes": cfg.eval.n_episodes}
    if isinstance(cfg.policy, PretrainedPolicyConfig):
        asked["batch_size"] = cfg.eval.num_envs
    return json.loads(json.dumps(json_safe(asked), default=str))


def saved_result(cfg: EvalConfig) -> dict | None:
    """The metrics.json in ``cfg.output_dir`` if it answers ``cfg``'s :func:`request`, else None:
    the main job and the baselines reuse it then, and run the evaluation again otherwise (another
    preset, crowd, policy setting or metric version)."""
    path = Path(cfg.output_dir) / "metrics.json"
    if not path.exists():
        return None
    result = json.loads(path.read_text())
    return result if result.get("request") == request(cfg) else None


def cli_args(argv: list[str]) -> list[str]:
    """``lerobot-crowdnav-eval``'s arguments as draccus reads them: ``--policy.path`` alone implies
    ``--policy.type=pretrained`` (lerobot's style)."""
    argv = list(argv)
    if any(a.startswith("--policy.path") for a in argv) and not any(a.startswith("--policy.type") for a in argv):
        argv.insert(0, "--policy.type=pretrained")
    return argv


def parse(argv: list[str]) -> EvalConfig:
    """The config of a ``lerobot-crowdnav-eval`` command line (without the program name)."""
    return draccus.parse(config_class=EvalConfig, args=cli_args(argv))


def evaluate(cfg: EvalConfig) -> dict:
    cfg.eval.validate()
    sim_cfg = cfg.env.resolve()
    policy = cfg.policy.name
    out = cfg.output_dir or Path("outputs/eval") / f"{sim_cfg.task}_{sim_cfg.preset}_{policy.replace('@', '_')}_{cfg.eval.split}"
    out = Path(out)
    metrics_path = out / "metrics.json"
    if metrics_path.exists() and not cfg.overwrite:
        raise FileExistsError(f"{metrics_path} exists; pass --overwrite=true to replace it or choose another --output_dir")
    env = CrowdNavVectorEnv(cfg.eval.num_envs, config=sim_cfg)
    actor = policy
    if isinstance(cfg.policy, PretrainedPolicyConfig):
        if cfg.policy.path is None:
            raise ValueError("--policy.type=pretrained needs --policy.path")
        actor = LearnedPolicy(cfg.policy.path, cfg.policy.device, sim_cfg.obs_dim, cfg.policy.seed, cfg.policy.use_ema,
                              cfg.policy.ddim_steps, sim_cfg.sentinel)
    start = time.perf_counter()
    records = run_episodes(env, actor, cfg.eval.split, cfg.eval.n_episodes, label=policy)
    elapsed = time.perf_counter() - start
    metrics = compute_metrics(records, sim_cfg.dt)
    result = {
        **metrics,
        "n_episodes": len(records),
        "request": request(cfg),
        "split": cfg.eval.split,
        "policy": policy,
        "policy_description": sim_cfg.orca_description if policy == "orca" else policy,
        "env": sim_cfg.to_dict(),
        "markdown": markdown_row(metrics, sim_cfg.bounded),
        "wall_time_s": elapsed,
        "machine": machine_description(),
        "episodes": [r.to_dict() for r in records],
    }
    out.mkdir(parents=True, exist_ok=True)
    tmp = metrics_path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(json_safe(result), indent=2, allow_nan=False))
    tmp.replace(metrics_path)
    if cfg.eval.n_videos:
        from ..sim.render import record_episode

        single = CrowdNavEnv(render_mode="rgb_array", config=sim_cfg)
        for seed in split_seeds(cfg.eval.split, min(cfg.eval.n_videos, cfg.eval.n_episodes)):
            step_policy = policy
            if callable(actor):
                actor.chunk = None  # a new episode
                step_policy = lambda o: actor(o[None], np.zeros(1, bool))[0]  # noqa: E731
            record_episode(single, out / "videos" / f"{policy.replace('@', '_')}_seed{seed}.gif", seed, step_policy)
    crowd = "" if (sim_cfg.human_policy, sim_cfg.robot_visible) == ("orca", False) else f", {sim_cfg.crowd_description}"
    print(f"\n{sim_cfg.task} ({sim_cfg.preset}{crowd}), policy {result['policy_description']}, "
          f"{len(records)} {cfg.eval.split} episodes:")
    print(markdown_header(sim_cfg.bounded))
    print(result["markdown"])
    print(f"wrote {metrics_path}")
    return result


def main(argv: list[str] | None = None) -> None:
    run_cli(EvalConfig, evaluate, cli_args(sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    main()
