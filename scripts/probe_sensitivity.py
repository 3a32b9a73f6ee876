"""Does a policy react to the crowd and the goal, or copy its own velocity? The copycat probe.

    python scripts/probe_sensitivity.py --env.task=BoundedCrowdNav-v0 \\
        --policy.path=orca --policy.path=models/lerobot-crowdnav/pdpo_bounded_h5 --output=probe.json

Behaviour cloning can learn "next action = current velocity" (observation entries 7-8 hold the
previous executed action) instead of the crowd and the goal. The probe measures it on the SAME
states for every policy: the ORCA teacher's own states on the first --episodes validation
episodes, one every --every steps, with a visible human and the robot moving (> 0.1 m/s). Each
state is perturbed in the simulator and observed again (``sim.observe()``); the unperturbed
response is taken the same way, so a pair differs only by the perturbation:

* velocity follow: the robot's current velocity is turned by +-20 degrees; the signed turn of the
  first action toward it, over 20 degrees (1: copies the velocity, 0: ignores it);
* goal turn: the goal is turned by +-30 degrees about the robot; the signed turn of the first
  action toward it, in degrees (30: follows the goal fully);
* R^2 of "first action = current velocity" on the unperturbed states (1 - SSE / SST).

Angles are the atan2 of the actions, differences wrapped to (-180, 180]; states whose unperturbed
action is slower than 0.05 m/s are skipped. A learned policy's action is the mean of --samples
clipped first actions, sampled with the same torch seed for every state and perturbation.
--policy.path is ``orca`` (the env's ORCA robot, the teacher) or a policy directory; repeat it
or give a list ``--policy.path=[orca,DIR]``. Prints a markdown table; --output writes JSON.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lerobot_crowdnav.cli import machine_description, run_cli
from lerobot_crowdnav.measure.episodes import LearnedPolicy, json_safe
from lerobot_crowdnav.sim.config import SEED_SPLITS, CrowdSimConfig, split_seeds
from lerobot_crowdnav.sim.engine import RUNNING, CrowdSim

MIN_ROBOT_SPEED = 0.1  # m/s: a robot at rest has no heading to copy
MIN_ACTION_SPEED = 0.05  # m/s: below this the action's angle is noise
TEACHER = "orca"


@dataclass
class PolicyPaths:
    # Policies to probe: orca (the env's ORCA robot, the teacher) and/or policy directories
    # (PDPO or any lerobot policy on observation.state). Repeat --policy.path=DIR or give a list
    # --policy.path=[orca,DIR].
    path: list[str] = field(default_factory=lambda: [TEACHER])


@dataclass
class ProbeConfig:
    """The copycat probe (scripts/probe_sensitivity.py): velocity follow (turn of the first action
    toward a turn of the current velocity, over that turn: 1 copies it, 0 ignores it), goal turn
    (turn toward a turned goal, degrees) and R^2 of "action = current velocity", on the ORCA
    teacher's validation states."""

    # Simulator: --env.task (BoundedCrowdNav-v0 | CrowdNav-v0), --env.preset (paper | crowdnavpp)
    # and any simulator field; the policies must have been trained on it.
    env: CrowdSimConfig = field(default_factory=CrowdSimConfig)
    policy: PolicyPaths = field(default_factory=PolicyPaths)
    # Validation episodes the teacher runs to give the states (the first n val seeds).
    episodes: int = 50
    # Keep one state every this many steps of each episode.
    every: int = 10
    # Learned policies: sampled first actions averaged per state (stochastic policies such as PDPO).
    samples: int = 8
    # Torch seed of the sampling noise, reset before every batch (the same noise for a state and
    # its perturbations).
    seed: int = 0
    # Torch device of the learned policies.
    device: str = "cpu"
    # States simulated and sampled together.
    batch_size: int = 64
    # Turn of the robot's current velocity, degrees (both signs are applied and averaged).
    velocity_rotation: float = 20.0
    # Turn of the goal about the robot, degrees (both signs).
    goal_rotation: float = 30.0
    # Also write the results as JSON here.
    output: Path | None = None

    def validate(self) -> None:
        size = SEED_SPLITS["val"][1] - SEED_SPLITS["val"][0]
        if not 1 <= self.episodes <= size:
            raise ValueError(f"--episodes must be in [1, {size}] (validation seeds), got {self.episodes}")
        for name in ("every", "samples", "batch_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name} must be >= 1, got {getattr(self, name)}")
        if not (0 < self.velocity_rotation < 180 and 0 < self.goal_rotation < 180):
            raise ValueError("--velocity_rotation and --goal_rotation must be in (0, 180) degrees")
        if not self.policy.path:
            raise ValueError("--policy.path: give at least one policy (orca or a directory)")
        self.env.resolve()


def rotate(v: np.ndarray, degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]], axis=1)


def turn_degrees(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Signed angle from ``before`` to ``after`` (counter-clockwise positive), in (-180, 180]."""
    d = np.degrees(np.arctan2(after[:, 1], after[:, 0]) - np.arctan2(before[:, 1], before[:, 0]))
    return 180.0 - (180.0 - d) % 360.0


def turn_velocity(degrees: float) -> Callable[[CrowdSim], None]:
    def perturb(sim: CrowdSim) -> None:
        sim.robot_vel[:] = rotate(sim.robot_vel, degrees)
    return perturb


def turn_goal(degrees: float) -> Callable[[CrowdSim], None]:
    def perturb(sim: CrowdSim) -> None:
        sim.robot_goal[:] = sim.robot_pos + rotate(sim.robot_goal - sim.robot_pos, degrees)
    return perturb


def collect_states(config: CrowdSimConfig, episodes: int, every: int) -> dict[str, np.ndarray]:
    """The teacher's own states (``CrowdSim.state_dict`` rows, stacked): the distribution the
    policies were cloned from, on validation seeds they were not trained on."""
    sim = CrowdSim(dataclasses.replace(config, compute_intrusion=False), episodes)
    sim.reset(split_seeds("val", episodes))
    alive = np.ones(episodes, bool)
    kept = []
    for t in range(sim.config.max_steps):
        if t % every == 0:
            keep = alive & (np.linalg.norm(sim.robot_vel, axis=1) > MIN_ROBOT_SPEED) & sim.visible.any(axis=1)
            if keep.any():
                kept.append({k: v[keep] for k, v in sim.state_dict().items()})
        alive &= sim.step(sim.clip_actions(sim.orca_actions())).event == RUNNING
        if not alive.any():
            break
    if not kept:
        raise ValueError(f"no state with a visible human and a moving robot in {episodes} episodes every {every} steps")
    return {k: np.concatenate([s[k] for s in kept]) for k in kept[0]}


def probe(states: dict[str, np.ndarray], config: CrowdSimConfig, act: Callable[[CrowdSim], np.ndarray],
          velocity_rotation: float = 20.0, goal_rotation: float = 30.0, batch_size: int = 64,
          bar: tqdm | None = None) -> dict:
    """The metrics of one policy ``act`` (a loaded and observed ``CrowdSim`` -> its ``(B, 2)``
    actions in m/s) on ``states`` (from :func:`collect_states`)."""
    base, velocity, vel_turn, goal_turn = [], [], [], []
    n = len(states["seeds"])
    for start in range(0, n, batch_size):
        chunk = {k: v[start:start + batch_size] for k, v in states.items()}
        sim = CrowdSim(config, len(chunk["seeds"]))

        def respond(perturb=None):
            sim.load_state_dict(chunk)
            if perturb is not None:
                perturb(sim)
            sim.observe()  # rebuilds the observation and drops the roll-out the teacher caches
            return np.asarray(act(sim), np.float64)

        a0 = respond()
        base.append(a0)
        velocity.append(chunk["robot_vel"])
        vel_turn.append(np.mean([s * turn_degrees(a0, respond(turn_velocity(s * velocity_rotation)))
                                 for s in (1, -1)], axis=0))
        goal_turn.append(np.mean([s * turn_degrees(a0, respond(turn_goal(s * goal_rotation)))
                                  for s in (1, -1)], axis=0))
        if bar is not None:
            bar.update(len(a0))
    base, velocity, vel_turn, goal_turn = (np.concatenate(x) for x in (base, velocity, vel_turn, goal_turn))
    ok = np.linalg.norm(base, axis=1) >= MIN_ACTION_SPEED
    if not ok.any():
        raise ValueError(f"every action is slower than {MIN_ACTION_SPEED} m/s: no angle to measure")
    follow = vel_turn[ok] / velocity_rotation
    sse = np.sum((base[ok] - velocity[ok]) ** 2)
    sst = np.sum((base[ok] - base[ok].mean(axis=0)) ** 2)
    return {"states": int(ok.sum()), "states_skipped_slow": int((~ok).sum()),
            "velocity_follow": float(follow.mean()), "velocity_follow_se": _se(follow),
            "goal_turn_deg": float(goal_turn[ok].mean()), "goal_turn_deg_se": _se(goal_turn[ok]),
            "r2_action_is_velocity": float(1.0 - sse / sst)}


def _se(x: np.ndarray) -> float:
    return float(x.std(ddof=1) / np.sqrt(len(x))) if len(x) > 1 else float("nan")


def teacher_act(sim: CrowdSim) -> np.ndarray:
    return sim.clip_actions(sim.orca_actions())


def learned_act(path: str, config: CrowdSimConfig, samples: int, seed: int, device: str) -> Callable[[CrowdSim], np.ndarray]:
    """A policy directory as an ``act``: the mean of ``samples`` clipped first actions, the noise
    reseeded every call so that a state and its perturbations share it."""
    policy = LearnedPolicy(Path(path), device, config.obs_dim, seed)

    def act(sim: CrowdSim) -> np.ndarray:
        policy.generator.manual_seed(seed)
        obs = np.repeat(sim.obs, samples, axis=0)
        actions = sim.clip_actions(policy(obs, np.ones(len(obs), bool)))
        return actions.reshape(-1, samples, 2).mean(axis=1)

    return act


def run(cfg: ProbeConfig) -> dict:
    cfg.validate()
    config = dataclasses.replace(cfg.env, compute_intrusion=False).resolve()
    acts = {p: teacher_act if p == TEACHER else learned_act(p, config, cfg.samples, cfg.seed, cfg.device)
            for p in cfg.policy.path}
    states = collect_states(config, cfg.episodes, cfg.every)
    n = len(states["seeds"])
    results = {}
    with tqdm(total=n * len(acts), unit="state", desc="probe") as bar:
        for name, act in acts.items():
            bar.set_postfix(policy=Path(name).name)
            results[name] = probe(states, config, act, cfg.velocity_rotation, cfg.goal_rotation, cfg.batch_size, bar)
    print(f"\n{config.task} ({config.preset}), {n} teacher states from {cfg.episodes} val episodes every {cfg.every} steps\n")
    print("| policy | states | velocity follow | goal turn (deg) | R^2 action = velocity |\n|---|---|---|---|---|")
    for name, r in results.items():
        print(f"| {name} | {r['states']} | {r['velocity_follow']:.3f} ± {r['velocity_follow_se']:.3f} | "
              f"{r['goal_turn_deg']:.2f} ± {r['goal_turn_deg_se']:.2f} | {r['r2_action_is_velocity']:.3f} |")
    summary = {"env": config.to_dict(), "episodes": cfg.episodes, "every": cfg.every, "samples": cfg.samples,
               "seed": cfg.seed, "velocity_rotation": cfg.velocity_rotation, "goal_rotation": cfg.goal_rotation,
               "teacher_states": n, "machine": machine_description(), "policies": results}
    if cfg.output:
        cfg.output.parent.mkdir(parents=True, exist_ok=True)
        cfg.output.write_text(json.dumps(json_safe(summary), indent=2))
    return summary


def merge_paths(argv: list[str]) -> list[str]:
    """Repeated ``--policy.path=X`` (each a path or a list) become the one list draccus parses."""
    paths, rest = [], []
    for arg in argv:
        if arg.startswith("--policy.path="):
            value = arg.split("=", 1)[1].strip()
            paths += [p.strip() for p in value.strip("[]").split(",") if p.strip()] if value.startswith("[") else [value]
        else:
            rest.append(arg)
    return rest + ([f"--policy.path=[{','.join(paths)}]"] if paths else [])


def main(argv: list[str] | None = None) -> None:
    run_cli(ProbeConfig, run, merge_paths(sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    main()
