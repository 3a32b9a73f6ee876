"""Each long job SIGKILLed at named write/rename sites (LEROBOT_CROWDNAV_FAULT), resumed, and
compared with an uninterrupted run; small sizes (tests/fault_injection.py, run as a script, runs them all, larger).
The main job's case is in tests/test_report.py (it shares the uninterrupted tiny run)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from dataclasses import dataclass

import numpy as np
import pyarrow.parquet as pq
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_crowdnav import fault
from lerobot_crowdnav.cli import run_cli
from lerobot_crowdnav.data.collect import main as collect_main
from lerobot_crowdnav.rl.finetune import main as finetune_main

import fault_injection as fi
from conftest import make_tiny_checkpoint

EPISODES, BATCH = 24, 8
CHUNK = {"action": [0, 0.25, 0.5, 0.75, 1.0]}


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("fault")


@pytest.fixture(scope="module")
def references(work):
    """Uninterrupted collections, keep=all and keep=success."""
    for keep in ("all", "success"):
        collect_main(fi.collect_argv(work / f"reference_{keep}", keep, EPISODES, BATCH))
    return {keep: work / f"reference_{keep}" for keep in ("all", "success")}


@pytest.mark.parametrize("keep, point, count", [
    ("all", "collect.create", 1),          # before the first write: no dataset yet
    ("all", "collect.data_written", 2),    # in the middle of a block's files
    ("success", "collect.renaming", 2),    # between a block's renames (stats in place, info not)
    ("success", "collect.committed", 1),   # right after a commit
])
def test_killed_collection_resumes_to_the_uninterrupted_dataset(work, references, keep, point, count):
    assert fi.collect_case(work, keep, point, count, references[keep], EPISODES, BATCH) == []
    resumed = LeRobotDataset(fi.REPO, root=work / f"collect_{keep}_{point}_{count}", delta_timestamps=CHUNK)
    reference = LeRobotDataset(fi.REPO, root=references[keep], delta_timestamps=CHUNK)
    assert resumed.meta.total_tasks == 1 and resumed.num_episodes == EPISODES
    last = int(resumed.meta.episodes[EPISODES - 1]["dataset_to_index"]) - 1
    for i in (0, last - 2, last):  # chunks inside an episode and padded at its end
        a, b = resumed[i], reference[i]
        assert a["task"] == b["task"] == "Navigate to the goal through the crowd."
        np.testing.assert_array_equal(a["action"].numpy(), b["action"].numpy())
        assert a["action_is_pad"].tolist() == b["action_is_pad"].tolist()
    assert resumed[last]["action_is_pad"].tolist() == [False, True, True, True, True]


def test_dataset_differences_sees_a_changed_stat(work, references, tmp_path):
    """The comparison the cases rely on can fail: one number changed in stats.json or in the
    frames is found, and nothing else."""
    import pyarrow as pa

    copy = tmp_path / "copy"
    shutil.copytree(references["all"], copy)
    assert fi.dataset_differences(references["all"], copy) == []
    original = (copy / "meta/stats.json").read_text()
    stats = json.loads(original)
    stats["action"]["mean"][0] += 1e-6
    (copy / "meta/stats.json").write_text(json.dumps(stats))
    assert fi.dataset_differences(references["all"], copy) == ["meta/stats.json"]
    (copy / "meta/stats.json").write_text(original)
    path = sorted(copy.glob("data/*/*.parquet"))[0]
    table = pq.read_table(path)
    actions = table["action"].to_pylist()
    actions[0][0] += 1e-6
    pq.write_table(table.set_column(table.schema.get_field_index("action"), "action",
                                    pa.array(actions, type=table.schema.field("action").type)), path)
    assert fi.dataset_differences(references["all"], copy) == ["data/*/*.parquet"]


@pytest.fixture(scope="module")
def finetuned(work):
    """A tiny checkpoint and an uninterrupted 64-step fine-tuning (checkpoints at 32 and 64)."""
    pretrained = make_tiny_checkpoint(work / "pretrained")
    reference = work / "reference_finetune"
    finetune_main(fi.finetune_argv(pretrained, reference, 64))
    return pretrained, reference


@pytest.mark.parametrize("point, count", [
    ("finetune.checkpoint_writing", 2),   # the second checkpoint half written: last stays at 32
    ("finetune.checkpoint_renamed", 2),   # renamed into place but not yet last
])
def test_killed_finetune_resumes_bitwise(work, finetuned, point, count):
    pretrained, reference = finetuned
    assert fi.finetune_case(work, pretrained, point, count, reference, 64) == []


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_ctrl_c_or_kill_checkpoints_the_iteration_then_resumes_bitwise(work, finetuned, sig):
    """Ctrl-C or ``kill`` in the middle of an iteration (sent by the process itself after its
    first rollout): the run finishes that iteration, saves a checkpoint there although none is
    due (``--save_freq=64``), and exits with how to resume; resumed, it ends where the
    uninterrupted run does (checkpoints every 32 steps there), bitwise."""
    pretrained, reference = finetuned
    out = work / f"finetune_{sig}"
    argv = [*fi.finetune_argv(pretrained, out, 64), "--save_freq=64"]
    proc = subprocess.run([sys.executable, "-m", "lerobot_crowdnav.rl.finetune", *argv], capture_output=True, text=True,
                          cwd=fi.ROOT, timeout=300, env={**os.environ, fault.ENV: f"ppo.collected:1:{sig}", "TQDM_DISABLE": "1"})
    assert proc.returncode == 1 and "interrupted: rerun the same command with --resume=true" in proc.stderr, proc.stderr[-2000:]
    assert f"{sig}: finishing this iteration and saving a checkpoint" in proc.stderr
    assert (out / "checkpoints" / "last").resolve().name == "000000032"
    fi.check_last_checkpoint(out)
    finetune_main([*argv, "--resume=true"])
    assert fi.finetune_differences(out, reference) == []


@pytest.mark.parametrize("kind, point, count", [("dataset", "hub.copying", 4),
                                                ("policy", "atomic.dir_exchanged", 1)])
def test_killed_push_leaves_the_old_or_the_new_repository(work, references, finetuned, kind, point, count):
    pretrained, reference = finetuned
    new, old = ((references["success"], references["all"]) if kind == "dataset" else
                (reference / "checkpoints/last/pretrained_model", pretrained))
    assert fi.hub_case(work, kind, new, old, point, count) == []


SIGTERMED_JOB = """
import os, signal, time
from dataclasses import dataclass
from lerobot_crowdnav.cli import run_cli

@dataclass
class NoOptions:
    n: int = 1

def job(cfg):
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(10)
    finally:
        print("cleanup ran", flush=True)

run_cli(NoOptions, job, [], "rerun it")
"""


@dataclass
class _NoOptions:
    n: int = 1


def test_sigterm_stops_a_resumable_command_through_its_cleanup():
    """``kill`` (SIGTERM) acts as Ctrl-C on a resumable command: its ``finally`` blocks run (the
    main job records the stage's wall time there) and it exits with how to resume (in a child
    process: without the handler SIGTERM ends it at once). In process: the handler is put back
    afterwards, and a command that cannot resume keeps the default."""
    done = subprocess.run([sys.executable, "-c", SIGTERMED_JOB], capture_output=True, text=True, timeout=60)
    assert (done.returncode, done.stdout) == (1, "cleanup ran\n"), done.stderr
    assert "interrupted: rerun it" in done.stderr
    before, seen = signal.getsignal(signal.SIGTERM), []
    run_cli(_NoOptions, lambda cfg: seen.append(signal.getsignal(signal.SIGTERM)), [], "rerun it")
    run_cli(_NoOptions, lambda cfg: seen.append(signal.getsignal(signal.SIGTERM)), [])
    assert seen[0] is not before and seen[1] is before and signal.getsignal(signal.SIGTERM) is before


def test_an_interrupted_stage_of_the_main_job_tells_how_to_resume_the_main_job():
    """The main job runs its stages' commands in-process, each through ``run_cli``: Ctrl-C in a
    stage gives the outer command's resume message, not the stage's own."""
    def stage(cfg):
        raise KeyboardInterrupt

    with pytest.raises(SystemExit, match="interrupted: rerun the main job") as exit_info:
        run_cli(_NoOptions, lambda cfg: run_cli(_NoOptions, stage, [], "rerun the stage"), [], "rerun the main job")
    assert "stage" not in str(exit_info.value)
    with pytest.raises(SystemExit, match="interrupted: rerun the stage"):  # the depth is back to 0
        run_cli(_NoOptions, stage, [], "rerun the stage")


def test_a_stage_killed_without_warning_keeps_its_time_so_far_and_a_rerun_adds_to_it(tmp_path):
    """The main job's stage wall times (the cards' table) survive a SIGKILL up to one heartbeat:
    the killed stage's time is on disk, and the rerun that completes it adds its own."""
    import json
    import time

    from lerobot_crowdnav.main.stages import StageRunner

    times = tmp_path / "stage_times.json"
    code = ("import time, sys\nfrom lerobot_crowdnav.main.stages import StageRunner\n"
            f"StageRunner(sys.argv[1], heartbeat_s=0.1).run('train', ['x'], False, lambda: time.sleep(60))\n")
    child = subprocess.Popen([sys.executable, "-c", code, str(times)])
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and json.loads(times.read_text() if times.exists() else "{}").get("train", 0) < 0.5:
        time.sleep(0.05)
    child.send_signal(signal.SIGKILL)
    child.wait()
    killed = json.loads(times.read_text())["train"]
    assert killed >= 0.5
    StageRunner(times, heartbeat_s=0.1).run("train", ["x"], False, lambda: time.sleep(0.3))
    total = json.loads(times.read_text())["train"]
    assert killed + 0.3 <= total < killed + 5
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind
    # The killed invocation's CPU time is unknown: the card says n/a rather than undercount it.
    from lerobot_crowdnav.data.hub import stage_time_table

    cpu = StageRunner(times).cpu_times()
    assert 0.3 <= cpu["train"]["wall_s"] < total - 0.4
    assert stage_time_table({"train": total}, cpu)[2].endswith("| n/a | n/a |")


def test_a_bc_run_killed_while_lerobot_moved_its_last_link_resumes_from_its_newest_checkpoint(tmp_path):
    """lerobot-train moves checkpoints/last by unlink, then symlink: killed in between, the run has
    numbered checkpoints and no `last`, and the main job would have started BC again from zero.
    The link is restored to the newest complete checkpoint (not to one cut short)."""
    from lerobot_crowdnav.checkpoint_files import PRETRAINED_MODEL, TRAINING_STATE, TRAINING_STEP
    from lerobot_crowdnav.main.training import restore_last_checkpoint

    checkpoints = tmp_path / "checkpoints"
    for step, complete in (("005000", True), ("010000", True), ("015000", False)):
        (checkpoints / step / PRETRAINED_MODEL).mkdir(parents=True)
        if complete:
            (checkpoints / step / TRAINING_STATE).mkdir()
            (checkpoints / step / TRAINING_STATE / TRAINING_STEP).write_text('{"step": %d}' % int(step))
    restore_last_checkpoint(checkpoints)
    assert (checkpoints / "last").resolve() == (checkpoints / "010000").resolve()
    (checkpoints / "last").unlink()
    (checkpoints / "last").symlink_to("020000")  # dangling
    restore_last_checkpoint(checkpoints)
    assert (checkpoints / "last").resolve() == (checkpoints / "010000").resolve()
    restore_last_checkpoint(tmp_path / "never_started" / "checkpoints")  # nothing to restore: no error


def test_a_best_found_after_the_last_checkpoint_waits_for_the_next_one(tmp_path):
    """best/ belongs to the trajectory a run resumes from: a new best is pending until the next
    checkpoint is in place; resumed before it, a best the interrupted run found later is dropped,
    one found up to the checkpoint (killed between the checkpoint and its promotion) is kept, and an
    old best left at the pending name by a kill right after the exchange never comes back."""
    import json
    from types import SimpleNamespace

    from lerobot_crowdnav.rl.checkpoints import Checkpoints

    acc = SimpleNamespace(is_main_process=True, process_index=0, wait_for_everyone=lambda: None)
    ckpts = Checkpoints(tmp_path, acc, 9)

    def best_at(env_steps: int) -> None:
        ckpts.save_best(lambda p: p.mkdir(parents=True), {"env_steps": env_steps})

    def checkpoint(env_steps: int) -> None:
        ckpts.save(env_steps, lambda p: p.mkdir(parents=True), {}, lambda state, r: None)

    def best() -> int | None:
        info = tmp_path / "best" / "best.json"
        return json.loads(info.read_text())["env_steps"] if info.exists() else None

    best_at(0)
    assert best() is None and ckpts.pending_best.exists()
    checkpoint(200)
    assert best() == 0 and not ckpts.pending_best.exists()
    best_at(300)  # then killed before the checkpoint at 400
    Checkpoints(tmp_path, acc, 9).settle_best(200)
    assert best() == 0 and not ckpts.pending_best.exists()
    best_at(300)
    Checkpoints(tmp_path, acc, 9).settle_best(300)  # its checkpoint was in place, its promotion not
    assert best() == 300
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "best.json").write_text(json.dumps({"env_steps": 0}))
    (tmp_path / "old").rename(ckpts.pending_best)  # the old best, at the pending name after the exchange
    Checkpoints(tmp_path, acc, 9).settle_best(400)
    assert best() == 300 and not ckpts.pending_best.exists()
