"""Fine-tuning checkpoints on disk and the rules for resuming from them.

    checkpoints/<env steps>/pretrained_model   the policy (the agent's ``save``) + the run's settings
                                               (finetune_config.json or train_ppo_config.json)
    checkpoints/<env steps>/training_state     optimizers.pt (optimizers, counters), and per process
                                               env_rank<r>.npz, rng_rank<r>.json
    checkpoints/last -> <latest>;  checkpoints/best/pretrained_model (+ best.json)

Every checkpoint is written under a hidden staging name and swapped in with one atomic rename
when complete (``fault.replace_dir``), so an interrupted save never leaves a half checkpoint
behind ``last`` or ``best``, nor loses the previous ``best``. A new best waits in
``.best.pending`` until the next checkpoint is in place: ``best`` then always belongs to the
trajectory the run resumes from (a run killed after a validation but before its next checkpoint
replays those steps, and on another device may not find that best again).
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import torch

from .. import fault
from ..checkpoint_files import BEST_INFO, PRETRAINED_MODEL, TRAINING_STATE

# Settings that must not change when a run is resumed, and the simulator fields that may (metrics
# only: the dynamics and rewards are the same either way).
RESUME_KEYS = ("env", "num_envs", "ppo", "seed", "env_seed")
RESUME_FREE_ENV = ("compute_intrusion",)


def resume_conflicts(saved: dict, now: dict, world_size: int, defaults: dict | None = None) -> list[str]:
    """The settings a resumed run changed (``saved``: the checkpoint's run settings file). A
    setting that the saved file lacks (added since it was written) counts at its value in
    ``defaults`` (the settings of a default-constructed config)."""
    defaults = defaults or {}

    def filled(k: str):
        value = saved.get(k)
        if isinstance(value, dict) and isinstance(defaults.get(k), dict):
            return {**{d: v for d, v in defaults[k].items() if d in now.get(k, {})}, **value}
        return value

    def compared(k: str, value):
        if k == "env" and isinstance(value, dict):
            return {d: v for d, v in value.items() if d not in RESUME_FREE_ENV}
        return value

    changed = [k for k in RESUME_KEYS if compared(k, filled(k)) != compared(k, now.get(k))]
    if saved.get("world_size", 1) != world_size:
        changed.append(f"number of processes ({saved.get('world_size', 1)} -> {world_size})")
    return changed


class Checkpoints:
    """Writes and reads the checkpoints of one run; the main process writes the shared parts,
    every process its own env and RNG state."""

    def __init__(self, root: Path, accelerator, name_width: int):
        self.root, self.acc, self.width = Path(root), accelerator, name_width
        self.rank = accelerator.process_index

    @property
    def last(self) -> Path:
        return self.root / "last"

    def save(self, env_steps: int, save_policy: Callable[[Path], None], shared: dict,
             save_rank_state: Callable[[Path, int], None]) -> Path:
        """``shared`` goes to training_state/optimizers.pt; ``save_rank_state(dir, rank)`` writes
        one process's own state."""
        name = f"{env_steps:0{self.width}d}"
        staging = self.root / f".{name}.tmp"
        state = staging / TRAINING_STATE
        if self.acc.is_main_process:
            shutil.rmtree(staging, ignore_errors=True)
            state.mkdir(parents=True)
            save_policy(staging / PRETRAINED_MODEL)
            fault.point("finetune.checkpoint_writing")
            torch.save(shared, state / "optimizers.pt")
        self.acc.wait_for_everyone()
        save_rank_state(state, self.rank)
        self.acc.wait_for_everyone()
        final = self.root / name
        if self.acc.is_main_process:  # complete, then in place, then named last: never a partial last
            fault.replace_dir(staging, final)
            fault.point("finetune.checkpoint_renamed")
            link = self.root / ".last.tmp"
            link.unlink(missing_ok=True)
            link.symlink_to(name)
            link.replace(self.last)
            fault.point("finetune.last_linked")
            self._promote_best()
        self.acc.wait_for_everyone()
        return final

    @property
    def pending_best(self) -> Path:
        return self.root / ".best.pending"

    def save_best(self, save_policy: Callable[[Path], None], info: dict) -> None:
        """Main process only: ``pretrained_model`` and ``best.json`` (``info``, with ``env_steps``)
        of a new best, which becomes ``best/`` at the next checkpoint."""
        staging = self.root / ".best.tmp"
        shutil.rmtree(staging, ignore_errors=True)
        save_policy(staging / PRETRAINED_MODEL)
        (staging / BEST_INFO).write_text(json.dumps(info, indent=2))
        fault.replace_dir(staging, self.pending_best)

    def settle_best(self, env_steps: int) -> None:
        """Main process, at the start of a run resumed at ``env_steps`` (0: from scratch): a pending
        best found up to there belongs to this trajectory (killed between the checkpoint and its
        promotion) and becomes ``best/``; one found later, by the interrupted run, is dropped."""
        self._promote_best(up_to=env_steps)

    def _promote_best(self, up_to: float = float("inf")) -> None:
        """``.best.pending`` becomes ``best/`` if it is newer than ``best/`` and found by ``up_to``
        env steps; otherwise it is dropped (also the old best that a kill right after the atomic
        exchange leaves at the pending name)."""
        if not self.pending_best.exists():
            return
        found = json.loads((self.pending_best / BEST_INFO).read_text())["env_steps"]
        best = self.root / "best" / BEST_INFO
        current = json.loads(best.read_text())["env_steps"] if best.exists() else -1
        if current < found <= up_to:
            fault.replace_dir(self.pending_best, self.root / "best")
        else:
            shutil.rmtree(self.pending_best)

    def load_shared(self) -> dict:
        return torch.load(self.last / TRAINING_STATE / "optimizers.pt", map_location=self.acc.device, weights_only=True)
