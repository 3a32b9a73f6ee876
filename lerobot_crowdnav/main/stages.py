"""The resumable stage runner of the main job: each stage runs the command a user would type
unless its output is complete, and its wall time is summed over every invocation that ran it, its
CPU time too (what it cost, however the machine was shared)."""

from __future__ import annotations

import json
import os
import resource
import threading
import time
from collections.abc import Callable
from pathlib import Path

from .. import fault
from ..evaluation.report import Stage

CPU_TIMES = "stage_cpu.json"
"""Beside ``stage_times.json``: ``{stage: {"cpu_s", "wall_s", "cores"}}``, the CPU seconds (user +
system, the main process and every subprocess it waited for) and wall seconds of the invocations
that ran the stage to their end or to a SIGTERM, and the logical cores each could use (its CPU
affinity). A SIGKILLed invocation adds wall time to ``stage_times.json`` (its heartbeats) but
nothing here, so ``wall_s`` short of the stage's wall time means its CPU time is partly unknown."""


def cpu_seconds() -> float:
    """CPU time so far of this process and of its finished (waited-for) subprocesses."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


class StageRunner:
    """Runs stages and records them: ``stages`` (this invocation's, in order: commands.json and the
    report's Stages table) and ``times_file`` (``stage_times.json``, every invocation's). A running
    stage's time is saved every ``heartbeat_s`` seconds too, so a process killed without warning
    (SIGKILL, a machine handed back) loses at most that much of it from the cards' wall times.
    Its CPU time goes to :data:`CPU_TIMES` beside ``times_file`` when the stage ends."""

    def __init__(self, times_file: Path, heartbeat_s: float = 60.0):
        self.times_file = Path(times_file)
        self.cpu_file = self.times_file.with_name(CPU_TIMES)
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
            start, cpu_start = time.perf_counter(), cpu_seconds()
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
                self._add_cpu_time(name, cpu_seconds() - cpu_start, elapsed)
            stage = Stage(name, argv, elapsed)
        self.stages[name] = stage
        return stage

    def wall_times(self) -> dict[str, float]:
        """Wall time of each stage summed over every invocation that ran it (a resumed stage's
        time includes the interrupted attempts, a SIGKILLed one up to its last heartbeat)."""
        return json.loads(self.times_file.read_text()) if self.times_file.exists() else {}

    def cpu_times(self) -> dict[str, dict]:
        """:data:`CPU_TIMES`'s records (empty for a run folder older than it)."""
        return json.loads(self.cpu_file.read_text()) if self.cpu_file.exists() else {}

    def _add_cpu_time(self, name: str, cpu_s: float, wall_s: float) -> None:
        records = self.cpu_times()
        old = records.get(name, {"cpu_s": 0.0, "wall_s": 0.0, "cores": []})
        records[name] = {"cpu_s": old["cpu_s"] + cpu_s, "wall_s": old["wall_s"] + wall_s,
                         "cores": sorted({*old["cores"], len(os.sched_getaffinity(0))})}
        fault.write_text(self.cpu_file, json.dumps(records, indent=2))

    def _set_wall_time(self, name: str, seconds: float, injectable: bool = True) -> None:
        """Record ``seconds`` as the stage's time so far (the heartbeat's writes are not fault points)."""
        times = self.wall_times()
        times[name] = seconds
        fault.write_text(self.times_file, json.dumps(times, indent=2), injectable)
