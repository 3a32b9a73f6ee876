"""Each long job SIGKILLed at named write/rename sites (LEROBOT_CROWDNAV_FAULT), resumed, and
compared with an uninterrupted run; small sizes (scripts/fault_injection.py runs them all, larger).
The main job's case is in tests/test_report.py (it shares the uninterrupted tiny run)."""

from __future__ import annotations

import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_crowdnav import fault_injection as fi
from lerobot_crowdnav.data.collect import main as collect_main
from lerobot_crowdnav.rl.finetune import main as finetune_main

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


def test_dataset_differences_sees_a_changed_stat(work, references):
    """The comparison the cases rely on can fail."""
    assert fi.dataset_differences(references["all"], references["success"]) != []


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


@pytest.mark.parametrize("kind, point, count", [("dataset", "hub.copying", 4),
                                                ("policy", "atomic.dir_exchanged", 1)])
def test_killed_push_leaves_the_old_or_the_new_repository(work, references, finetuned, kind, point, count):
    pretrained, reference = finetuned
    new, old = ((references["success"], references["all"]) if kind == "dataset" else
                (reference / "checkpoints/last/pretrained_model", pretrained))
    assert fi.hub_case(work, kind, new, old, point, count) == []
