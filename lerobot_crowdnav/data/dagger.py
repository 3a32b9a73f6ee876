"""DAgger rounds for PDPO's pretraining: the learner drives, the ORCA demonstrator labels.

Behaviour cloning from the demonstrations alone learns to copy the robot's current velocity (the
previous action, in the observation) instead of reacting to the crowd: on the demonstrator's own
states the copy explains almost all of the next action. A DAgger round (Ross et al., AISTATS 2011)
rolls the current policy out in the batched simulator and labels the states *it* visits, where
its velocity is its own, with the demonstrator's action chunk from there: the simulator's state is
saved, the ORCA robot drives H steps, the state is restored and the learner goes on. The humans
ignore the robot, so that chunk is exactly what the demonstrator would have executed from the
learner's state.

Each labelled state becomes a short episode of the dataset, the demonstrator's H steps from it
(``observation.state``, ``action``, ``next.reward`` as in the demonstrations; ``next.done`` marks
the snippet's end), so the stock ``lerobot-train`` reads the chunk through its delta timestamps like
any demonstration, padded where the demonstrator reaches the goal early. Snippets in which the
demonstrator itself collides or runs out of the episode's time are left out (the demonstrations
keep successes only, for the same reason). A round is one committed block of the dataset, its
learner episodes a seed block of their own (``DAGGER_SEED_BASE + round * 1,000,000``, train
split); ``meta/crowdnav_collection.json`` (``dagger``) and the dataset card record every round.

    python -m lerobot_crowdnav.data.dagger --policy_path=CKPT --root=DATASET --round=1 --episodes=500
    lerobot-train --config_path=CKPT/train_config.json --resume=true --steps=N   # train on the aggregate
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .. import fault
from ..checkpoint_files import POLICY_CONFIG
from ..cli import run_cli
from ..sim.config import DAGGER_ROUND_SEEDS as ROUND_SEEDS, DAGGER_SEED_BASE, SEED_SPLITS, CrowdSimConfig
from ..sim.engine import EVENT_NAMES, RUNNING, SUCCESS, CrowdSim
from .dataset import CARD_FILE, COLLECTION_FILE, DemonstrationWriter, collection_complete

CARD_MARKER = "\n<!-- dagger rounds -->\n"


@dataclass
class DaggerConfig:
    # The policy that drives (a pretrained_model directory, e.g. lerobot-train's
    # checkpoints/last/pretrained_model).
    policy_path: Path | None = None
    # The dataset to aggregate into: a collection made by collect_orca.py (earlier rounds included).
    root: Path | None = None
    # Round number (>= 1): picks the learner's seed block; a round already in the dataset is skipped.
    round: int = 1
    # Learner episodes rolled out in this round.
    episodes: int = 500
    # Label every k-th state the learner visits (1: all).
    every: int = 1
    # Demonstrator steps per labelled state (default: the policy's action horizon H).
    horizon: int | None = None
    # Environments stepped together.
    batch_size: int = 64
    # Torch device of the policy.
    device: str = "cpu"
    # Seed of the policy's sampling noise.
    seed: int = 0

    def validate(self) -> None:
        if self.policy_path is None or not (Path(self.policy_path) / POLICY_CONFIG).exists():
            raise FileNotFoundError(f"--policy_path={self.policy_path}: no config.json (a pretrained_model directory)")
        if self.root is None or not (Path(self.root) / COLLECTION_FILE).exists():
            raise FileNotFoundError(f"--root={self.root}: not a collection made by collect_orca.py ({COLLECTION_FILE})")
        if not collection_complete(self.root):
            raise ValueError(f"--root={self.root}: the collection is incomplete (no dataset card); complete it with "
                             "collect_orca.py --resume=true first: no demonstration can follow a round")
        rounds = (SEED_SPLITS["train"][1] - DAGGER_SEED_BASE) // ROUND_SEEDS  # blocks left in the train split
        if not 1 <= self.round < rounds:
            raise ValueError(f"--round must be >= 1 (and below {rounds}), got {self.round}")
        for name in ("episodes", "every", "batch_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name} must be >= 1, got {getattr(self, name)}")
        if self.episodes > ROUND_SEEDS:
            raise ValueError(f"--episodes must be at most {ROUND_SEEDS:,} (a round's seed block)")
        if self.horizon is not None and self.horizon < 1:
            raise ValueError(f"--horizon must be >= 1, got {self.horizon}")


def teacher_snippets(sim: CrowdSim, slots: np.ndarray, horizon: int) -> list[dict]:
    """The demonstrator's ``horizon`` steps from the current state of each slot in ``slots``,
    the simulator left as it was. A snippet stops early where the demonstrator's episode ends;
    it is dropped where that end is a collision or a timeout (kept: running on, or the goal)."""
    saved = sim.state_dict()
    obs, act, rew = [], [], []
    event = np.full(sim.num_envs, RUNNING)
    length = np.zeros(sim.num_envs, np.int64)
    for _ in range(horizon):
        live = event == RUNNING
        obs.append(sim.obs.copy())
        a = sim.clip_actions(sim.orca_actions())
        res = sim.step(a)
        act.append(a)
        rew.append(res.reward)
        length += live
        event = np.where(live, res.event, event)
    sim.load_state_dict(saved)
    obs, act, rew = np.stack(obs, 1), np.stack(act, 1), np.stack(rew, 1)  # (B, horizon, ...)
    return [{"seed": int(sim.seeds[b]), "event": EVENT_NAMES[event[b]], "success": bool(event[b] == SUCCESS),
             "obs": obs[b, :length[b]], "action": act[b, :length[b]], "reward": rew[b, :length[b]]}
            for b in slots if event[b] in (RUNNING, SUCCESS)]


def learner_round(sim: CrowdSim, policy, seeds: list[int], every: int, horizon: int) -> tuple[list[dict], list[str]]:
    """Roll ``policy`` out on ``seeds`` (each once) and label every ``every``-th state it visits;
    returns the snippets and the learner episodes' events."""
    b = sim.num_envs
    if len(seeds) < b:
        raise ValueError(f"{len(seeds)} learner episodes cannot fill {b} environments")
    queue = list(seeds[b:])
    sim.reset(seeds[:b])
    active = np.ones(b, bool)
    t = np.zeros(b, np.int64)
    fresh = np.ones(b, bool)
    snippets, events = [], []
    bar = tqdm(total=len(seeds), desc="dagger learner episodes", unit="ep")
    while active.any():
        label = np.flatnonzero(active & (t % every == 0))
        if len(label):
            snippets += teacher_snippets(sim, label, horizon)
        res = sim.step(sim.clip_actions(policy(sim.obs.copy(), fresh)))
        t += 1
        ended = np.flatnonzero(active & (res.event != RUNNING))
        fresh[:] = False
        for i in ended:
            events.append(EVENT_NAMES[res.event[i]])
            bar.update(1)
            if queue:
                sim.reset([queue.pop(0)], [i])
                t[i], fresh[i] = 0, True
            else:
                active[i] = False
        bar.set_postfix(snippets=len(snippets), sr=f"{np.mean([e == 'success' for e in events]) if events else 0:.3f}")
    bar.close()
    return snippets, events


def dagger(cfg: DaggerConfig) -> dict:
    from ..measure.episodes import LearnedPolicy

    cfg.validate()
    root = Path(cfg.root)
    collection = json.loads((root / COLLECTION_FILE).read_text())
    rounds = collection.get("dagger", [])
    if any(r["round"] == cfg.round for r in rounds):
        print(f"[dagger] round {cfg.round} is already in {root}: skipped")
        return next(r for r in rounds if r["round"] == cfg.round)
    sim_cfg = CrowdSimConfig(**collection["env"]).resolve()
    writer = DemonstrationWriter(root, collection["repo_id"], sim_cfg, collection, resume=True)
    policy_cfg = json.loads((Path(cfg.policy_path) / POLICY_CONFIG).read_text())
    horizon = cfg.horizon or policy_cfg.get("horizon", 1)
    first_seed = DAGGER_SEED_BASE + cfg.round * ROUND_SEEDS
    start = time.perf_counter()
    committed = [row["episode_index"] for block in writer.committed_blocks() for row in block
                 if first_seed <= row["seed"] < first_seed + ROUND_SEEDS]
    first_episode = min(committed, default=writer.info.total_episodes)
    if committed:  # committed, then interrupted before its record
        snippets, events = None, None
    else:
        sim = CrowdSim(sim_cfg, min(cfg.batch_size, cfg.episodes))
        policy = LearnedPolicy(Path(cfg.policy_path), cfg.device, sim_cfg.obs_dim, seed=cfg.seed)
        snippets, events = learner_round(sim, policy, list(range(first_seed, first_seed + cfg.episodes)), cfg.every, horizon)
        writer.append(snippets)
    record = {"round": cfg.round, "policy": str(Path(cfg.policy_path).resolve()), "learner_episodes": cfg.episodes,
              "learner_seeds": [first_seed, first_seed + cfg.episodes - 1], "every": cfg.every, "horizon": horizon,
              "first_episode_index": first_episode, "snippets": writer.info.total_episodes - first_episode,
              "learner_outcomes": None if events is None else {e: events.count(e) for e in EVENT_NAMES[1:]},
              "frames": None if snippets is None else int(sum(len(s["action"]) for s in snippets)),
              "wall_time_s": time.perf_counter() - start}
    collection["dagger"] = rounds + [record]
    fault.write_text(root / COLLECTION_FILE, json.dumps(collection, indent=2))
    _update_card(root, collection["dagger"])
    print(json.dumps(record, indent=2))
    return record


def _update_card(root: Path, rounds: list[dict]) -> None:
    """The dataset card's DAgger section, rewritten from the rounds' records."""
    card = root / CARD_FILE
    text = card.read_text().split(CARD_MARKER)[0] if card.exists() else ""
    lines = [CARD_MARKER, "## DAgger rounds", "",
             "Episodes from `first_episode_index` on are not demonstrations: each is the demonstrator's chunk "
             "(its first H steps) from a state visited by the policy being trained, labelled by "
             "`python -m lerobot_crowdnav.data.dagger` (snippets where the demonstrator collides or times out are left out; "
             "`seed` is the learner's episode).", "",
             "| round | learner episodes (seeds) | learner outcomes | every | H | snippets (from episode) | frames | policy |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rounds:
        outcomes = ", ".join(f"{k} {v}" for k, v in (r["learner_outcomes"] or {}).items()) or "n/a"
        lines.append(f"| {r['round']} | {r['learner_episodes']} ({r['learner_seeds'][0]}-{r['learner_seeds'][1]}) | "
                     f"{outcomes} | {r['every']} | {r['horizon']} | {r['snippets']} ({r['first_episode_index']}) | "
                     f"{r['frames'] if r['frames'] is not None else 'n/a'} | `{r['policy']}` |")
    fault.write_text(card, text + "\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> None:
    run_cli(DaggerConfig, dagger, argv, "rerun the same command: a round whose block was not committed starts over")


if __name__ == "__main__":
    main()
