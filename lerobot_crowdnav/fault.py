"""Fault injection for the resume tests, and the atomic file operations those tests hold to.

``LEROBOT_CROWDNAV_FAULT=<point>:<n>`` makes the process SIGKILL itself the n-th time (1-based) it
reaches ``fault.point("<point>")``: a kill at an exact write or rename site, with no timing.
``<point>:<n>:SIGINT`` sends Ctrl-C there instead (what a user's interrupt does at that moment). Unset
(always, outside tests), ``point`` is a dictionary lookup. The named points sit at the real sites
(see docs/resume.md for the list); the harness that drives them, ``tests/fault_injection.py``, is
test code and lives with the tests.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import signal
from pathlib import Path

ENV = "LEROBOT_CROWDNAV_FAULT"
_hits: dict[str, int] = {}


def point(name: str) -> None:
    """Die here, as a SIGKILL would take the process, if ``ENV`` names this point and hit count."""
    spec = os.environ.get(ENV)
    if not spec:
        return
    target, count, *sig = spec.split(":")
    if target != name:
        return
    _hits[name] = _hits.get(name, 0) + 1
    if _hits[name] == int(count):
        os.kill(os.getpid(), getattr(signal, sig[0]) if sig else signal.SIGKILL)


def write_text(path: Path, text: str, injectable: bool = True) -> None:
    """Write a file so that readers see either its old content or the whole new one.
    ``injectable=False``: no fault point, for writes whose number depends on timing (a heartbeat)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    if injectable:
        point("atomic.file")
    tmp.replace(path)


_RENAME_EXCHANGE = 2
_renameat2 = getattr(ctypes.CDLL(None, use_errno=True), "renameat2", None) if os.name == "posix" else None


def replace_dir(staged: Path, target: Path) -> None:
    """Move the complete directory ``staged`` to ``target``, replacing any ``target`` in one atomic
    step (Linux renameat2 RENAME_EXCHANGE): a reader, or a kill, sees the old directory or the new
    one, never neither. Elsewhere the old directory is moved aside first (a short gap)."""
    staged, target = Path(staged), Path(target)
    if not target.exists():
        staged.replace(target)
        return
    if _renameat2 is not None:
        at_cwd = -100  # AT_FDCWD
        if _renameat2(at_cwd, os.fsencode(staged), at_cwd, os.fsencode(target), _RENAME_EXCHANGE) != 0:
            err = ctypes.get_errno()
            raise OSError(err, os.strerror(err), str(target))
        point("atomic.dir_exchanged")
        shutil.rmtree(staged)  # now the old directory
        return
    old = staged.with_name(staged.name + ".old")
    target.replace(old)
    staged.replace(target)
    shutil.rmtree(old)
