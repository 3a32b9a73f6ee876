"""What every command-line entry point of the project shares: draccus parsing (``--help``,
``--config_path``), bad input reported as one ``error: ...`` line instead of a traceback, and the
machine description that timed outputs (metrics, benchmark, report) record."""

from __future__ import annotations

import os
import platform
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from subprocess import CalledProcessError
from typing import TypeVar

import draccus
from draccus.utils import DecodingError

T = TypeVar("T")
USER_ERRORS = (ValueError, FileExistsError, FileNotFoundError)
_depth = 0  # run_cli calls in progress: the main job runs its stages' commands in-process


def run_cli(config_class: type[T], run: Callable[[T], object], argv: list[str] | None = None,
            interrupted: str | None = None) -> None:
    """Parse ``argv`` (default: the process's) into ``config_class`` and call ``run`` with it.
    ``interrupted``: what to tell the user on Ctrl-C (how to resume), if the command can resume.
    A resumable command takes SIGTERM (``kill``, a batch system's time limit) as Ctrl-C, so that
    its cleanup runs: the main job then records the interrupted stage's wall time."""
    global _depth
    try:
        cfg = draccus.parse(config_class=config_class, args=list(sys.argv[1:] if argv is None else argv))
    except DecodingError as e:  # a value of the wrong type: one line, not draccus' chained tracebacks
        raise SystemExit(f"error: {e}") from None
    previous = None
    if interrupted is not None and threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _interrupt)
    _depth += 1
    try:
        run(cfg)
    except USER_ERRORS as e:
        raise SystemExit(f"error: {e}") from None
    except CalledProcessError as e:
        raise SystemExit(f"error: a stage command failed ({e.returncode}): {' '.join(map(str, e.cmd))}") from None
    except KeyboardInterrupt:
        if interrupted is None or _depth > 1:  # a stage of the main job: the outer command says how to resume
            raise
        raise SystemExit(f"interrupted: {interrupted}") from None
    finally:
        _depth -= 1
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


class Interrupt:
    """Set by :func:`deferred_interrupt`'s handler: a stop was asked for."""

    requested: bool = False


@contextmanager
def deferred_interrupt(what: str) -> Iterator[Interrupt]:
    """Ctrl-C or SIGTERM inside the block sets ``requested`` on the yielded flag instead of
    raising, so that a long loop can stop where its state is whole (a training iteration's end:
    save, then ``raise KeyboardInterrupt``); a second one raises at once. ``what`` tells the user
    what the loop does before it stops. Outside the main thread signals are left alone."""
    flag = Interrupt()
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum, frame) -> None:
        if flag.requested:
            raise KeyboardInterrupt
        flag.requested = True
        print(f"\n{signal.Signals(signum).name}: {what} (again to stop at once)", file=sys.stderr, flush=True)

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield flag
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def machine_description() -> str:
    """The CPU model and its logical cores, for reports, cards and benchmarks; when this process
    may run on fewer of them (taskset, a container's cpuset), how many: a figure measured on one
    pinned core says so."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            model = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    total = os.cpu_count()
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else total
    return f"{model}, {total} logical cores" + (f" (pinned to {usable})" if usable < total else "")
