"""The resumable stage runner of the main job: each stage runs the command a user would type
unless its output is complete, and its wall time is summed over every invocation that ran it."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

from .. import fault
from ..evaluation.report import Stage


class StageRunner:
    """Runs stages and records them: ``stages`` (this invocation's, in order: commands.json and the
    report's Stages table) and ``times_file`` (``stage_times.json``, every invocation's)."""

    def __init__(self, times_file: Path):
        self.times_file = Path(times_file)
        self.stages: dict[str, Stage] = {}

    def run(self, name: str, argv: list[str], done: bool, run: Callable[[], object]) -> Stage:
        """Run the stage unless its output is complete; record its command (and wall time)."""
        if done:
            print(f"[main] {name}: complete, skipped")
            stage = Stage(name, argv)
        else:
            print(f"[main] {name}: {' '.join(argv)}", flush=True)
            start = time.perf_counter()
            try:
                run()
            finally:
                elapsed = time.perf_counter() - start
                self._add_wall_time(name, elapsed)
            stage = Stage(name, argv, elapsed)
        self.stages[name] = stage
        return stage

    def wall_times(self) -> dict[str, float]:
        """Wall time of each stage summed over every invocation that ran it (a resumed stage's
        time includes the interrupted attempts, Ctrl-C and SIGTERM included; not SIGKILL)."""
        return json.loads(self.times_file.read_text()) if self.times_file.exists() else {}

    def _add_wall_time(self, name: str, seconds: float) -> None:
        times = self.wall_times()
        times[name] = times.get(name, 0.0) + seconds
        fault.write_text(self.times_file, json.dumps(times, indent=2))
