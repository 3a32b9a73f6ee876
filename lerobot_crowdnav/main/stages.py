"""The resumable stage runner of the main job: each stage runs the command a user would type
unless its output is complete, and its wall time is summed over every invocation that ran it."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from pathlib import Path

from .. import fault
from ..evaluation.report import Stage


class StageRunner:
    """Runs stages and records them: ``stages`` (this invocation's, in order: commands.json and the
    report's Stages table) and ``times_file`` (``stage_times.json``, every invocation's). A running
    stage's time is saved every ``heartbeat_s`` seconds too, so a process killed without warning
    (SIGKILL, a machine handed back) loses at most that much of it from the cards' wall times."""

    def __init__(self, times_file: Path, heartbeat_s: float = 60.0):
        self.times_file = Path(times_file)
        self.heartbeat_s = heartbeat_s
        self.stages: dict[str, Stage] = {}

    def run(self, name: str, argv: list[str], done: bool, run: Callable[[], object]) -> Stage:
        """Run the stage unless its output is complete; record its command (and wall time)."""
        if done:
            print(f"[main] {name}: complete, skipped")
            stage = Stage(name, argv)
        else:
            print(f"[main] {name}: {' '.join(argv)}", flush=True)
            before = self.wall_times().get(name, 0.0)
            start = time.perf_counter()
            stop = threading.Event()

            def heartbeat() -> None:
                while not stop.wait(self.heartbeat_s):
                    self._set_wall_time(name, before + time.perf_counter() - start, injectable=False)

            beat = threading.Thread(target=heartbeat, name=f"stage time: {name}", daemon=True)
            beat.start()
            try:
                run()
            finally:
                stop.set()
                beat.join()
                elapsed = time.perf_counter() - start
                self._set_wall_time(name, before + elapsed)
            stage = Stage(name, argv, elapsed)
        self.stages[name] = stage
        return stage

    def wall_times(self) -> dict[str, float]:
        """Wall time of each stage summed over every invocation that ran it (a resumed stage's
        time includes the interrupted attempts, a SIGKILLed one up to its last heartbeat)."""
        return json.loads(self.times_file.read_text()) if self.times_file.exists() else {}

    def _set_wall_time(self, name: str, seconds: float, injectable: bool = True) -> None:
        """Record ``seconds`` as the stage's time so far (the heartbeat's writes are not fault points)."""
        times = self.wall_times()
        times[name] = seconds
        fault.write_text(self.times_file, json.dumps(times, indent=2), injectable)
