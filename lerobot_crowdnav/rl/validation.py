"""Validation of an actor-critic on the validation seeds (deterministic actions), and the
training episodes' statistics summed over processes."""

from __future__ import annotations

import numpy as np
import torch

from ..measure.episodes import run_episodes
from ..measure.metrics import compute_metrics
from ..sim.engine import EVENT_NAMES
from .loop import restart_memory

EVENTS = EVENT_NAMES[1:]  # how an episode ends (not "running")


def validate(agent, env, n_episodes: int, dt: float, device: torch.device) -> dict[str, float]:
    """The first ``n_episodes`` val seeds, one batched env, no exploration noise (fixed sampling
    seed 0, so every validation of the same weights gives the same numbers). ``val/intrusion_rate``
    (ITR) only where ``env`` runs the intrusion test: without it the count would read 0."""
    generator = torch.Generator(device=device).manual_seed(0)
    memory = agent.initial_memory(env.num_envs)

    def actor(obs: np.ndarray, fresh: np.ndarray) -> np.ndarray:
        nonlocal memory
        memory = restart_memory(memory, fresh)
        step = agent.act(torch.as_tensor(obs, dtype=torch.float32), memory, False, generator)
        memory = step.memory
        return step.action.numpy().astype(np.float64)

    records = run_episodes(env, actor, "val", n_episodes, progress=False)
    m = compute_metrics(records, dt)
    itr = {"val/intrusion_rate": m["itr"]} if env.config.compute_intrusion else {}
    return {"val/success_rate": m["sr"], "val/collision_rate": m["cr"], "val/human_collision_rate": m["cr_human"],
            "val/timeout_rate": m["tr"], "val/navigation_time": m["nt"], **itr,
            "val/episode_return": float(np.mean([r.episode_return for r in records]))}


def episode_stats(episodes: list[dict], accelerator) -> dict[str, float]:
    """Rates, mean return, its prediction-penalty part and mean length of the episodes that ended in
    an iteration, all processes. Return minus penalty is what CrowdNav++'s training log reports."""
    counts = torch.tensor([len(episodes), *[sum(e["event"] == ev for e in episodes) for ev in EVENTS],
                           *[sum(e[k] for e in episodes) for k in ("return", "prediction_penalty", "length")]],
                          dtype=torch.float64, device=accelerator.device)
    c = accelerator.reduce(counts, reduction="sum").cpu().tolist()
    if not c[0]:
        return {"train/episodes": 0}
    n, *events, ret, pred, length = c
    return {"train/episodes": int(n), **{f"train/{ev}_rate": k / n for ev, k in zip(EVENTS, events, strict=True)},
            "train/episode_return": ret / n, "train/prediction_penalty": pred / n, "train/episode_length": length / n}
