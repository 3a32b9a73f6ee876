"""The paper's action-chunk figures from a trained policy checkpoint.

    python -m lerobot_crowdnav.evaluation.figures --policy.path=outputs/train/<run>/checkpoints/last/pretrained_model \\
        --env.task=BoundedCrowdNav-v0 --seed=2000000000 --steps=0,4,8,12,16 --n_samples=32 \\
        --output_dir=outputs/figures/<run>

Runs one episode with the PDPO policy replanning every step (receding horizon: sample a chunk,
execute its first action) and, at the chosen steps, keeps the observation, the executed chunk and
``n_samples`` more chunks sampled for the same observation. Writes ``storyboard.png`` (the planned
path of the executed chunk, step by step) and ``multimodality.png`` (the spread of the sampled
chunks): see :func:`lerobot_crowdnav.measure.plots.plot_storyboard` and ``plot_multimodality``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


from ..cli import run_cli
from ..measure.episodes import LearnedPolicy
from ..measure.plots import plot_multimodality, plot_storyboard
from ..sim.config import SEED_SPLITS, CrowdSimConfig
from ..sim.envs import CrowdNavEnv


def record_snapshots(policy_path: str | Path, sim_cfg: CrowdSimConfig, seed: int, steps: list[int],
                     n_samples: int, device: str = "cpu", policy_seed: int = 0) -> list[dict]:
    """Run episode ``seed`` with the policy and return, for each of ``steps`` the episode reaches,
    ``{"step", "t" (s), "obs" (obs_dim,), "chunk" (H, 2) m/s (the executed one),
    "chunks" (n_samples, H, 2) m/s}``.

    Deterministic given ``policy_seed``: the executed chunks draw from one generator (so the
    episode is the one ``lerobot-crowdnav-eval --policy.seed`` runs) and the extra samples from
    another, so ``n_samples`` does not change the episode."""
    import torch

    steps = sorted(set(int(s) for s in steps))
    if not steps or steps[0] < 0:
        raise ValueError(f"steps must be non-empty step indices >= 0, got {steps}")
    if n_samples < 1:
        raise ValueError(f"n_samples must be >= 1, got {n_samples}")
    sim_cfg = sim_cfg.resolve()
    actor = LearnedPolicy(Path(policy_path), device, sim_cfg.obs_dim, policy_seed, sentinel=sim_cfg.sentinel)
    extra = torch.Generator(device=device).manual_seed(policy_seed + 1)
    env = CrowdNavEnv(config=sim_cfg)
    obs, _ = env.reset(seed=seed)
    wanted = set(steps)
    snapshots = []
    for step in range(steps[-1] + 1):
        with torch.inference_mode():
            batch = actor.pre({"observation.state": torch.as_tensor(obs[None], dtype=torch.float32)})
            chunk = actor.post(actor.policy.predict_action_chunk(batch, generator=actor.generator))[0].cpu().numpy()
            if step in wanted:
                chunks = actor.post(actor.policy.sample_chunks(batch, n_samples, generator=extra))[0].cpu().numpy()
                snapshots.append({"step": step, "t": step * sim_cfg.dt, "obs": obs.copy(), "chunk": chunk,
                                  "chunks": chunks})
        obs, _, terminated, truncated, _ = env.step(chunk[0])
        if terminated or truncated:
            break
    return snapshots


def parse_steps(text: str) -> list[int]:
    """``"0,4,8"`` -> ``[0, 4, 8]`` (distinct, increasing, >= 0)."""
    try:
        steps = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise ValueError(f"--steps must be comma-separated step indices like 0,4,8, got {text!r}") from None
    if not steps or min(steps) < 0 or steps != sorted(set(steps)):
        raise ValueError(f"--steps must be distinct increasing step indices >= 0, got {text!r}")
    return steps


@dataclass
class FigurePolicyConfig:
    """The trained PDPO policy drawn: --policy.path=<checkpoint>."""

    # Checkpoint directory: <output_dir>/checkpoints/<step>/pretrained_model (or a hub-format directory).
    path: Path | None = None
    # Torch device for the policy.
    device: str = "cpu"
    # Seed of the policy's sampling noise: the same seed draws the same figures.
    seed: int = 0


@dataclass
class FiguresConfig:
    """python -m lerobot_crowdnav.evaluation.figures: storyboard.png and multimodality.png of one episode."""

    # Simulator: --env.task (CrowdNav-v0 | BoundedCrowdNav-v0), --env.preset (paper | crowdnavpp)
    # and any simulator field.
    env: CrowdSimConfig = field(default_factory=CrowdSimConfig)
    policy: FigurePolicyConfig = field(default_factory=FigurePolicyConfig)
    # Episode seed (default: the first test seed).
    seed: int = SEED_SPLITS["test"][0]
    # Steps to draw, comma-separated (dt = 0.25 s apart); steps after the episode's end are skipped.
    steps: str = "0,4,8,12,16"
    # Chunks sampled per drawn step for multimodality.png.
    n_samples: int = 32
    # Where storyboard.png and multimodality.png go (default: outputs/figures/<task>_seed<seed>).
    output_dir: Path | None = None


def make_figures(cfg: FiguresConfig) -> tuple[Path, Path]:
    """Record the snapshots and draw both figures; returns their paths."""
    if cfg.policy.path is None:
        raise ValueError("--policy.path=<checkpoint> is required")
    if not Path(cfg.policy.path).is_dir():
        raise FileNotFoundError(f"--policy.path={cfg.policy.path}: no such directory")
    steps = parse_steps(cfg.steps)
    sim_cfg = cfg.env.resolve()
    snapshots = record_snapshots(cfg.policy.path, sim_cfg, cfg.seed, steps, cfg.n_samples,
                                 cfg.policy.device, cfg.policy.seed)
    if not snapshots:
        raise ValueError(f"episode {cfg.seed} ended before step {steps[0]}")
    if len(snapshots) < len(steps):
        print(f"episode {cfg.seed} ended before step {steps[len(snapshots)]}; "
              f"drawing steps {[s['step'] for s in snapshots]}")
    out = Path(cfg.output_dir or Path("outputs/figures") / f"{sim_cfg.task}_seed{cfg.seed}")
    walls = sim_cfg.arena_size if sim_cfg.bounded else None
    title = f"{sim_cfg.task}, episode {cfg.seed}"
    story = plot_storyboard(snapshots, out / "storyboard.png", sim_cfg.sensing_range, sim_cfg.dt,
                            title=title, arena_size=walls)
    multi = plot_multimodality(snapshots, out / "multimodality.png", sim_cfg.sensing_range, sim_cfg.dt,
                               title=title, arena_size=walls)
    return story, multi


def main(argv: list[str] | None = None) -> None:
    run_cli(FiguresConfig, lambda cfg: [print(f"wrote {path}") for path in make_figures(cfg)], argv)


if __name__ == "__main__":
    main()
