"""DAgger rounds: the demonstrator's chunk from a learner's state, the simulator left as it was,
and a round aggregated into the LeRobotDataset that lerobot reads chunk by chunk."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from conftest import HF_DATASETS_CACHE, make_tiny_checkpoint
from lerobot_crowdnav.data.collect import main as collect_main
from lerobot_crowdnav.data.dagger import ROUND_SEEDS, main as dagger_main, teacher_snippets
from lerobot_crowdnav.data.dataset import COLLECTION_FILE
from lerobot_crowdnav.data.hub import policy_card
from lerobot_crowdnav.sim.config import DAGGER_SEED_BASE, CrowdSimConfig
from lerobot_crowdnav.sim.engine import HUMAN_COLLISION, RUNNING, SUCCESS, WALL_COLLISION, CrowdSim


def test_teacher_snippets_are_the_demonstrators_chunk_from_the_learners_state():
    cfg = CrowdSimConfig(task="BoundedCrowdNav-v0", preset="paper").resolve()
    sim = CrowdSim(cfg, 32)
    sim.reset(np.arange(32) + 123)
    for _ in range(3):  # a learner that walks 45 degrees off its goal: its velocity is its own
        a = sim.straight_actions() @ np.array([[0.7, 0.7], [-0.7, 0.7]])
        sim.step(a)
    learner_velocity = sim.clip_actions(a)
    before = sim.state_dict()
    horizon = 24
    snippets = {s["seed"]: s for s in teacher_snippets(sim, np.arange(32), horizon)}
    for key, value in sim.state_dict().items():  # the learner goes on from where it was
        np.testing.assert_array_equal(value, before[key], err_msg=key)

    ref = CrowdSim(cfg, 32)  # the demonstrator driving from the same states
    ref.load_state_dict(before)
    obs, act, event, length = [], [], np.full(32, RUNNING), np.zeros(32, int)
    for _ in range(horizon):
        live = event == RUNNING
        obs.append(ref.obs.copy())
        act.append(ref.clip_actions(ref.orca_actions()))
        res = ref.step(act[-1])
        length += live
        event = np.where(live, res.event, event)
    collided = np.isin(event, [HUMAN_COLLISION, WALL_COLLISION])
    assert collided.any() and (~collided).any() and (event == SUCCESS).sum() + (event == RUNNING).sum() == (~collided).sum()
    for b in range(32):
        seed = int(before["seeds"][b])
        assert (seed in snippets) == (not collided[b])  # the demonstrator's collisions are left out
        if seed in snippets:
            s = snippets[seed]
            n = length[b]
            np.testing.assert_array_equal(s["obs"], np.stack(obs)[:n, b])
            np.testing.assert_allclose(s["action"], np.stack(act)[:n, b])
            assert s["success"] == (event[b] == SUCCESS)
            np.testing.assert_allclose(s["obs"][0, 7:9], learner_velocity[b], rtol=1e-6)  # the learner's state


def test_a_round_is_refused_on_an_incomplete_collection(tmp_path):
    """A collection killed before its card can only be completed by collect_orca.py --resume,
    which refuses once a round is in it: the round must not start (nor write a card that marks
    the collection complete)."""
    (tmp_path / "policy").mkdir()
    (tmp_path / "policy" / "config.json").write_text("{}")
    root = tmp_path / "ds"
    (root / COLLECTION_FILE).parent.mkdir(parents=True)
    (root / COLLECTION_FILE).write_text(json.dumps({"seed": 0, "episodes": 8}))
    with pytest.raises(SystemExit, match="incomplete"):
        dagger_main([f"--policy_path={tmp_path / 'policy'}", f"--root={root}"])
    assert not (root / "README.md").exists()


def test_a_round_aggregates_labelled_chunks_that_lerobot_reads(tmp_path):
    policy = make_tiny_checkpoint(tmp_path)  # untrained PDPO, H = 5, and its 8-episode dataset at tmp_path/ds
    root = tmp_path / "ds"
    info = json.loads((root / "meta/info.json").read_text())
    n_demos, demo_frames = info["total_episodes"], info["total_frames"]
    argv = [f"--policy_path={policy}", f"--root={root}", "--round=2", "--episodes=4", "--every=7", "--batch_size=4"]
    dagger_main(argv)
    record = json.loads((root / COLLECTION_FILE).read_text())["dagger"][0]

    ds = LeRobotDataset(f"local/{tmp_path.name}", root=root, delta_timestamps={"action": [k / 4 for k in range(5)]})
    assert ds.meta.total_episodes == n_demos + record["snippets"] and record["snippets"] > 0
    lo = DAGGER_SEED_BASE + 2 * ROUND_SEEDS
    episodes = ds.meta.episodes
    for e in range(n_demos, ds.meta.total_episodes):
        row = episodes[e]
        assert lo <= row["seed"] < lo + 4 and 1 <= row["length"] <= 5
        item = ds[row["dataset_from_index"]]
        n = row["length"]
        frames = ds.hf_dataset.select(range(row["dataset_from_index"], row["dataset_to_index"]))
        np.testing.assert_array_equal(item["action"][:n].numpy(), np.stack(frames["action"]))
        assert not item["action_is_pad"][:n].any() and item["action_is_pad"][n:].all()
    assert ds.meta.total_frames == demo_frames + record["frames"]
    assert "## DAgger rounds" in (root / "README.md").read_text()

    # A rerun skips the round; a round committed but not recorded (killed in between) is recorded, not redone.
    dagger_main(argv)
    collection = json.loads((root / COLLECTION_FILE).read_text())
    assert len(collection["dagger"]) == 1
    del collection["dagger"]
    (root / COLLECTION_FILE).write_text(json.dumps(collection))
    dagger_main(argv)
    again = json.loads((root / COLLECTION_FILE).read_text())["dagger"]
    assert [r["first_episode_index"] for r in again] == [n_demos]
    assert again[0]["snippets"] == record["snippets"]
    assert json.loads((root / "meta/info.json").read_text())["total_episodes"] == n_demos + record["snippets"]
    with pytest.raises(SystemExit, match="--round must be >= 1"):
        dagger_main([*argv[:2], "--round=0"])


def test_the_main_job_pretrains_with_dagger_rounds_in_segments(tmp_path):
    from lerobot_crowdnav.main.config import MainConfig
    from lerobot_crowdnav.main.training import Training

    cfg = MainConfig(run="dagger", output_root=tmp_path, models=None, tasks=["BoundedCrowdNav-v0"], demos=8,
                     bc_steps=4, bc_batch_size=16, horizons=[1], bc_dagger_at=[2, 9], bc_dagger_episodes=2,
                     bc_args=["--policy.velocity_dropout=0.5"], demonstrator="current_state")
    cfg.validate()
    job = Training(cfg)
    task = "BoundedCrowdNav-v0"
    job.collect(task)
    assert job.collect(task).wall_time_s is None  # the demonstrator's collection is complete: skipped
    cached = set(Path(HF_DATASETS_CACHE).rglob("*.arrow"))  # the process's (the suite's) datasets cache
    job.pretrain(task, 1, 1000)
    # lerobot-train's Arrow copies of the dataset went to the run folder, deleted after each segment
    assert set(Path(HF_DATASETS_CACHE).rglob("*.arrow")) == cached and not job.paths.datasets_cache.exists()
    data = job.pretrain_dataset(task, 1, 1000)
    assert data != job.paths.dataset_root(task)
    rounds = json.loads((data / COLLECTION_FILE).read_text())["dagger"]
    assert [r["round"] for r in rounds] == [1]  # the round at step 9 is past the budget: none
    demos = json.loads((job.paths.dataset_root(task) / COLLECTION_FILE).read_text())
    assert "dagger" not in demos
    # the chosen demonstrator (not the preset's look-ahead robot) collects, and so labels the rounds
    assert demos["env"]["orca_robot"] == json.loads((data / COLLECTION_FILE).read_text())["env"]["orca_robot"] == "current_state"
    last = job.paths.train_dir(task, 1, 1000) / "checkpoints" / "last"
    assert json.loads((last / "training_state/training_step.json").read_text())["step"] == 4
    train_cfg = json.loads((last / "pretrained_model/train_config.json").read_text())
    assert train_cfg["dataset"]["root"] == str(data) and train_cfg["policy"]["velocity_dropout"] == 0.5
    # published under its own name, never the look-ahead demonstrations' (the preset's here)
    assert train_cfg["dataset"]["repo_id"] == "local/crowdnav_orca_bounded_current_state"
    assert Training(dataclasses.replace(cfg, demonstrator=None)).repo_id(task) == "local/crowdnav_orca_bounded"
    assert Path(rounds[0]["policy"]).parent.name.lstrip("0") == "2"  # the round's learner: the step-2 checkpoint
    card = str(policy_card(last / "pretrained_model", "org/x"))  # the card says how it was pretrained
    assert "demonstrations of CrowdNav++'s current-state ORCA robot" in card  # the chosen demonstrator
    assert ("; the robot's own velocity (the previous action) hidden from the policy in 50% of the training samples; "
            f"1 DAgger round aggregated into the demonstrations (2 episodes driven by the policy being trained, "
            f"{rounds[0]['snippets']:,} of their states labelled") in card
    stage = job.pretrain(task, 1, 1000)
    assert stage.wall_time_s is None  # complete: skipped
    # its recorded command (report, commands.json) is the whole pretraining: first segment, round, resume
    first, rnd, resume = " ".join(stage.argv).split(" && ")
    assert first.startswith("lerobot-train ") and "--steps=2 " in first
    assert rnd.startswith("python -m lerobot_crowdnav.data.dagger ") and "--round=1 " in rnd and f"--root={data} " in rnd
    assert resume.startswith("lerobot-train --config_path=") and resume.endswith(" --resume=true --steps=4")
    with pytest.raises(ValueError, match="bc_dagger_at"):
        MainConfig(models=None, bc_dagger_at=[0]).validate()
    with pytest.raises(ValueError, match="--demonstrator must be one of"):
        MainConfig(models=None, demonstrator="current-state").validate()


def test_more_demonstrations_are_refused_after_a_round_and_nothing_changes(tmp_path):
    """collect_orca.py --resume would go on from the last committed seed, a learner's, count the
    snippets as demonstrations and rewrite the card without its DAgger section; also for a round
    committed and killed before its record."""
    policy = make_tiny_checkpoint(tmp_path)  # its 8-episode dataset at tmp_path/ds
    root = tmp_path / "ds"
    dagger_main([f"--policy_path={policy}", f"--root={root}", "--round=1", "--episodes=4", "--every=7", "--batch_size=4"])
    resume = ["--episodes=16", "--batch_size=8", f"--root={root}", f"--repo_id=local/{tmp_path.name}", "--resume=true"]

    def files() -> dict[Path, bytes]:
        return {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}

    for recorded in (True, False):
        if not recorded:
            collection = json.loads((root / COLLECTION_FILE).read_text())
            del collection["dagger"]
            (root / COLLECTION_FILE).write_text(json.dumps(collection))
        before = files()
        with pytest.raises(SystemExit, match="DAgger rounds were aggregated into .*collect the demonstrations you need "
                                             "into a new --root, then run the DAgger rounds on it again"):
            collect_main(resume)
        assert files() == before
