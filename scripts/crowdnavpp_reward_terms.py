"""Where a CrowdNav++ policy's episode reward comes from: its terms, per outcome.

    python scripts/crowdnavpp_reward_terms.py --policy=outputs/train_ppo/crowdnavpp_original/checkpoints/last/pretrained_model
    python scripts/crowdnavpp_reward_terms.py --policy=straight --task=BoundedCrowdNav-v0 --preset=paper

runs ``--episodes`` episodes of a crowdnavpp checkpoint (sampling its Gaussian as in training, or
its mean with ``--explore=false``) or of a built-in robot (``straight``, ``orca``) and splits every
episode's return into the reward's terms (docs/simulator.md, "Reward and termination"): the
terminal reward (success, collision, timeout), progress (the potential term), discomfort, and the
prediction penalty, which the step info reports apart. Return minus prediction penalty is what the
reference's training log calls an episode's reward (docs/crowdnavpp.md), so this is how a run's
reward at one checkpoint is compared with that log where the run's own log lacks the split. For a
checkpoint it also prints the speed its Gaussian's mean commands before the env's clip (10th, 50th
and 90th percentile over all steps). Episodes run from ``--seed`` on, consecutive seeds (default:
the validation split's first). Prints a markdown table; ``--output_json`` also keeps the numbers.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lerobot_crowdnav.cli import run_cli
from lerobot_crowdnav.sim.config import SEED_SPLITS, CrowdSimConfig
from lerobot_crowdnav.sim.engine import EVENT_NAMES, RUNNING

BUILT_IN = ("straight", "orca")
TERMS = ("terminal", "progress", "discomfort", "prediction_penalty")
OUTCOMES = EVENT_NAMES[1:]


@dataclass
class RewardTermsConfig:
    # A crowdnavpp pretrained_model directory, or a built-in robot: straight | orca.
    policy: str = "straight"
    # The env: CrowdNav-v0 | BoundedCrowdNav-v0.
    task: str = "CrowdNav-v0"
    # The simulator preset (crowdnavpp: the reference's own scene; paper).
    preset: str = "crowdnavpp"
    # Episodes to run (the first that end).
    episodes: int = 300
    # Episodes stepped together.
    num_envs: int = 16
    # A checkpoint's actions: sampled from its Gaussian as in training (true), or its mean (false).
    explore: bool = True
    # First episode seed; the next episodes take the seeds after it.
    seed: int = SEED_SPLITS["val"][0]
    # Seed of the Gaussian's sampling noise.
    noise_seed: int = 0
    # Also write the numbers to this JSON file.
    output_json: Path | None = None


@dataclass
class Terms:
    """Mean per episode of a group of episodes (all, or one outcome)."""

    share: float
    episodes: int
    steps: float
    episode_return: float
    terminal: float
    progress: float
    discomfort: float
    prediction_penalty: float

    @property
    def without_penalty(self) -> float:
        return self.episode_return - self.prediction_penalty


def _actor(cfg: RewardTermsConfig, sim_cfg: CrowdSimConfig, env):
    """act(obs, starts) -> actions (``starts``: the slots whose episode just began; None at first);
    and the list it appends the mean's speeds to (a checkpoint only)."""
    if cfg.policy in BUILT_IN:
        return (lambda obs, starts: env.expert_actions(cfg.policy)), None
    import torch

    from lerobot_crowdnav.rl.crowdnavpp import check_compatible, load_agent

    agent = load_agent(Path(cfg.policy)).eval()
    check_compatible(agent.policy, sim_cfg)
    memory = [agent.initial_memory(cfg.num_envs)]
    generator = torch.Generator().manual_seed(cfg.noise_seed)
    speeds: list[np.ndarray] = []

    def act(obs, starts):
        mem = memory[0] if starts is None else torch.where(torch.as_tensor(starts)[:, None],
                                                           agent.initial_memory(cfg.num_envs), memory[0])
        obs_t = torch.as_tensor(obs, dtype=torch.float32)
        with torch.no_grad():
            mean = agent.net.step(obs_t, mem)[0]
        step = agent.act(obs_t, mem, cfg.explore, generator)
        memory[0] = step.memory
        speeds.append(np.linalg.norm(mean.numpy(), axis=1))
        return step.action.numpy().astype(np.float64)

    return act, speeds


def measure(cfg: RewardTermsConfig) -> dict:
    """The episodes' terms: overall and per outcome, plus the mean's speed percentiles."""
    from lerobot_crowdnav.sim.envs import CrowdNavVectorEnv

    if cfg.episodes < 1 or cfg.num_envs < 1:
        raise ValueError("--episodes and --num_envs must be >= 1")
    if cfg.policy not in BUILT_IN and not Path(cfg.policy).is_dir():
        raise FileNotFoundError(f"--policy={cfg.policy}: not a pretrained_model directory, nor one of {', '.join(BUILT_IN)}")
    sim_cfg = CrowdSimConfig(task=cfg.task, preset=cfg.preset).resolve()
    env = CrowdNavVectorEnv(cfg.num_envs, config=sim_cfg)
    obs, _ = env.reset(seed=list(range(cfg.seed, cfg.seed + cfg.num_envs)))
    act, speeds = _actor(cfg, sim_cfg, env)
    acc = np.zeros((cfg.num_envs, len(TERMS) + 1))  # the terms, then the steps
    ended: list[tuple[str, np.ndarray]] = []
    starts = None
    bar = tqdm(total=cfg.episodes, desc="episodes", unit="ep")
    while len(ended) < cfg.episodes:
        obs, reward, term, trunc, info = env.step(act(obs, starts))
        done = term | trunc
        penalty = info["prediction_penalty"]
        base = reward - penalty
        near = info["min_distance"] < sim_cfg.discomfort_dist
        acc[:, 0] += np.where(done, base, 0.0)
        acc[:, 1] += np.where(~done & ~near, base, 0.0)
        acc[:, 2] += np.where(~done & near, base, 0.0)
        acc[:, 3] += penalty
        acc[:, 4] += 1
        for b in np.flatnonzero(done):
            ended.append((EVENT_NAMES[int(info["final_info"]["event"][b])], acc[b].copy()))
            acc[b] = 0.0
        bar.update(min(int(done.sum()), cfg.episodes - bar.n))
        starts = done
    bar.close()
    ended = ended[:cfg.episodes]

    def group(rows: list[np.ndarray]) -> Terms | None:
        if not rows:
            return None
        x = np.mean(rows, axis=0)
        return Terms(len(rows) / len(ended), len(rows), float(x[4]), float(x[:4].sum()), *map(float, x[:4]))

    out = {"all": group([x for _, x in ended])}
    out |= {o: group([x for e, x in ended if e == o]) for o in OUTCOMES}
    if speeds:
        out["mean_speed_percentiles"] = [float(v) for v in np.percentile(np.concatenate(speeds), [10, 50, 90])]
    return out


def table(result: dict) -> str:
    head = ["episodes", "share (%)", "steps", "return", "terminal", "progress", "discomfort", "prediction penalty",
            "return without prediction penalty"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name in ("all", *OUTCOMES):
        t = result.get(name)
        if t is not None:
            cells = [f"{name} ({t.episodes})", f"{100 * t.share:.1f}", f"{t.steps:.1f}",
                     *(f"{v:.2f}" for v in (t.episode_return, *(getattr(t, k) for k in TERMS), t.without_penalty))]
            lines.append("| " + " | ".join(cells) + " |")
    if "mean_speed_percentiles" in result:
        lines.append("\nspeed commanded by the Gaussian's mean, m/s (10th / 50th / 90th percentile): "
                     + " / ".join(f"{v:.2f}" for v in result["mean_speed_percentiles"]))
    return "\n".join(lines)


def run(cfg: RewardTermsConfig) -> str:
    result = measure(cfg)
    text = table(result)
    print(text)
    if cfg.output_json is not None:
        Path(cfg.output_json).parent.mkdir(parents=True, exist_ok=True)
        plain = {k: (asdict(v) | {"without_penalty": v.without_penalty}) if isinstance(v, Terms) else v
                 for k, v in result.items()}
        Path(cfg.output_json).write_text(json.dumps({"config": {k: str(v) for k, v in asdict(cfg).items()}, **plain},
                                                    indent=1))
    return text


def main(argv: list[str] | None = None) -> None:
    run_cli(RewardTermsConfig, run, argv)


if __name__ == "__main__":
    main()
