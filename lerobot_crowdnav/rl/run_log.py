"""What a fine-tuning run reports, on the main process: progress.jsonl (a record per iteration),
TensorBoard scalars, optionally W&B, and training_curves.png at the end."""

from __future__ import annotations

import json
import math
from pathlib import Path

from .. import fault
from ..measure.episodes import json_safe


class RunLog:
    def __init__(self, out: Path, enabled: bool, env_steps: int, resume: bool, wandb_cfg, config: dict):
        """``env_steps``: the run's counter at its start. A resumed run keeps what was logged up to
        it and drops what the interrupted run logged after its last checkpoint: TensorBoard's step
        is the env step, so its purge starts right after it."""
        self.enabled, self.out = enabled, Path(out)
        self.records: list[dict] = []
        self.writer = self.wandb = None
        if not enabled:
            return
        self.out.mkdir(parents=True, exist_ok=True)
        self.progress = self.out / "progress.jsonl"
        if resume and self.progress.exists():  # keep the history up to the checkpoint resumed
            self.records = [r for r in read_progress(self.out) if r["env_steps"] <= env_steps]
        fault.write_text(self.progress, "".join(json.dumps(r) + "\n" for r in self.records))
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(self.out / "tensorboard", purge_step=env_steps + 1 if resume else 0)
        if wandb_cfg.enable:
            import wandb

            self.wandb = wandb.init(project=wandb_cfg.project, mode=wandb_cfg.mode, dir=str(self.out), config=config,
                                    name=self.out.name, id=self.out.name.replace("/", "_"), resume="allow")

    def log(self, record: dict) -> None:
        """``record`` holds ``iteration``, ``env_steps`` and scalars (numbers; NaN kept as null)."""
        if not self.enabled:
            return
        self.records.append(record)
        with self.progress.open("a") as f:
            f.write(json.dumps(json_safe(record), allow_nan=False) + "\n")
        for k, val in record.items():
            if isinstance(val, (int, float)) and k not in ("iteration", "env_steps") and math.isfinite(val):
                self.writer.add_scalar(k, val, record["env_steps"])
        self.writer.flush()
        if self.wandb is not None:
            self.wandb.log({k: v for k, v in record.items() if isinstance(v, (int, float))}, step=record["env_steps"])

    def close(self) -> None:
        if not self.enabled:
            return
        self.writer.close()
        if self.wandb is not None:
            self.wandb.finish()
        from ..measure.plots import plot_finetune_curves

        plot_finetune_curves({self.out.name: self.records}, self.out / "training_curves.png")


def read_progress(run: Path) -> list[dict]:
    """The records of ``<run>/progress.jsonl`` (a fine-tuning or PPO run's output directory). A
    last line cut short (the process killed while appending it) is left out; a bad line before it
    is an error naming the file and line."""
    path = Path(run) / "progress.jsonl"
    lines = path.read_text().splitlines()
    records = []
    for number, line in enumerate(lines, start=1):
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as e:
            if number < len(lines):
                raise ValueError(f"{path}:{number} is not a JSON record ({e}): the run's log is damaged") from None
    return records


def env_steps_by_device(records: list[dict]) -> dict[str, dict[str, float]]:
    """A run's env steps and training wall time (s) per device its iterations ran on, in order of
    first use, from its ``progress.jsonl`` records; a record without ``device`` (written before
    records kept it) counts as ``cpu``."""
    by_device: dict[str, dict[str, float]] = {}
    steps, wall = 0, 0.0
    for r in records:
        if r.get("time/wall_s") is None:  # the starting validation: no iteration
            continue
        d = by_device.setdefault(r.get("device", "cpu"), {"env_steps": 0, "wall_s": 0.0})
        d["env_steps"] += r["env_steps"] - steps
        d["wall_s"] += r["time/wall_s"] - wall
        steps, wall = r["env_steps"], r["time/wall_s"]
    return by_device
