"""ORCA demonstration datasets: lerobot's own loaders, chunked action targets against a replay,
statistics for normalization, resume after a kill, refusals, and the hub-format directory."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import torch
from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.processor import NormalizerProcessorStep

from lerobot_crowdnav import fault
from lerobot_crowdnav.data.collect import main as collect_main
from lerobot_crowdnav.data.hub import main as push_main
from lerobot_crowdnav.sim.envs import CrowdNavEnv

REPO = "local/test_orca"
H = 5  # PDPO's action chunk
CHUNK = {"action": [k / 4 for k in range(H)]}
ROOT = Path(__file__).resolve().parents[1]


def collect(root, *args, episodes=24, batch_size=8):
    keep = [] if any(a.startswith("--keep") for a in args) else ["--keep=all"]
    collect_main([f"--episodes={episodes}", f"--batch_size={batch_size}", f"--root={root}",
                  f"--repo_id={REPO}", *keep, *args])


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("orca") / "ds"
    collect(root)
    return root


def test_lerobot_loads_chunks_equal_to_a_replay(dataset_root):
    ds = LeRobotDataset(REPO, root=dataset_root, delta_timestamps=CHUNK)
    assert ds.num_episodes == 24 and ds.fps == 4
    assert ds.features["observation.state"]["names"][:2] == ["robot_px", "robot_py"]
    env = CrowdNavEnv(task="BoundedCrowdNav-v0", compute_intrusion=False)
    for ep in range(0, 24, 5):
        meta = ds.meta.episodes[ep]
        lo, hi = meta["dataset_from_index"], meta["dataset_to_index"]
        # Replay the episode's seed through the gymnasium env with the built-in ORCA robot.
        obs, _ = env.reset(seed=int(meta["seed"]))
        observations, actions = [], []
        while True:
            action = env.sim.clip_actions(env.expert_action("orca"))
            observations.append(obs)
            actions.append(action)
            obs, _, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                break
        assert hi - lo == len(actions) == meta["length"]
        assert info["event"] == meta["event"]
        actions = np.asarray(actions, np.float32)
        for t in range(len(actions)):
            item = ds[lo + t]
            np.testing.assert_array_equal(item["observation.state"].numpy(), observations[t])
            n_real = min(H, len(actions) - t)
            np.testing.assert_array_equal(item["action"][:n_real].numpy(), actions[t:t + n_real])
            assert item["action_is_pad"].tolist() == [False] * n_real + [True] * (H - n_real)
        assert bool(ds[hi - 1]["next.done"]) and not bool(ds[hi - 2]["next.done"])
        assert bool(ds[hi - 1]["next.success"]) == (meta["event"] == "success")
    # Seeds are the consecutive train seeds from --seed (default 0), in order.
    assert [ds.meta.episodes[i]["seed"] for i in range(24)] == list(range(24))


def test_stats_feed_lerobot_normalization(dataset_root):
    meta = LeRobotDatasetMetadata(REPO, root=dataset_root)
    assert meta.stats["observation.state"]["mean"].shape == (269,)
    assert set(meta.stats["action"]) >= {"min", "max", "mean", "std", "q01", "q99"}
    ds = LeRobotDataset(REPO, root=dataset_root)
    states = torch.stack([ds[i]["observation.state"] for i in range(len(ds))])
    np.testing.assert_allclose(meta.stats["observation.state"]["mean"], states.mean(0).numpy(), rtol=1e-4, atol=1e-4)
    features = {"observation.state": PolicyFeature(FeatureType.STATE, (269,)),
                "action": PolicyFeature(FeatureType.ACTION, (2,))}
    norm = NormalizerProcessorStep.from_lerobot_dataset(
        ds, features, {FeatureType.STATE: NormalizationMode.MEAN_STD, FeatureType.ACTION: NormalizationMode.MIN_MAX})
    out = norm({"observation": {"observation.state": ds[3]["observation.state"][None]},
                "action": ds[3]["action"][None]})
    assert torch.isfinite(out["action"]).all() and out["action"].abs().max() <= 1 + 1e-5


def test_keep_success_keeps_only_successes(tmp_path):
    root = tmp_path / "succ"
    collect(root, "--keep=success", episodes=10)
    meta = LeRobotDatasetMetadata(REPO, root=root)
    events = [meta.episodes[i]["event"] for i in range(meta.total_episodes)]
    assert events == ["success"] * 10


def _committed(root: Path) -> int:
    try:
        return json.loads((root / "meta/info.json").read_text())["total_episodes"]
    except (OSError, ValueError, KeyError):
        return 0


def test_ctrl_c_commits_the_block_then_resumes_to_the_same_dataset(tmp_path):
    """Ctrl-C while the third block is being written (SIGKILL at each write site:
    tests/test_fault_injection.py). The signal is sent by the process itself at that write site:
    48 episodes take less time than any outside poll could aim at."""
    root = tmp_path / "killed"
    cmd = [sys.executable, str(ROOT / "datasets_scripts/collect_orca.py"), "--episodes=48",
           "--batch_size=4", f"--root={root}", f"--repo_id={REPO}", "--keep=all"]
    proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, timeout=120,
                          env={**os.environ, "TQDM_DISABLE": "1", fault.ENV: "collect.data_written:3:SIGINT"})
    err = proc.stderr
    assert proc.returncode != 0
    partial = _committed(root)
    assert partial == 12, "the block being written when Ctrl-C came is committed, nothing after it"
    assert "--resume" in err
    ds = LeRobotDataset(REPO, root=root)  # what was committed loads
    assert ds.num_episodes == partial and len(ds) == ds.meta.total_frames

    with pytest.raises(SystemExit, match="--resume"):
        collect(root, episodes=48, batch_size=4)
    collect(root, "--resume=true", episodes=48, batch_size=4)
    full = tmp_path / "uninterrupted"
    collect(full, episodes=48, batch_size=4)
    a, b = LeRobotDataset(REPO, root=root), LeRobotDataset(REPO, root=full)
    assert a.num_episodes == b.num_episodes == 48
    assert [a.meta.episodes[i]["seed"] for i in range(48)] == list(range(48))
    for key in ("observation.state", "action", "next.reward", "index", "episode_index"):
        np.testing.assert_array_equal(np.asarray(a.hf_dataset[key]), np.asarray(b.hf_dataset[key]))


def test_the_card_counts_what_the_dataset_holds_after_a_resume_asking_for_fewer(tmp_path):
    """A resume with a smaller --episodes keeps every committed episode; the card must say so
    (its episode count, seeds and frame count describe the same episodes)."""
    root = tmp_path / "fewer"
    collect(root, episodes=4, batch_size=2)
    collect(root, "--resume=true", episodes=2, batch_size=2)
    meta = LeRobotDatasetMetadata(REPO, root=root)
    assert meta.total_episodes == 4
    card = (root / "README.md").read_text()
    assert f"**Episodes:** 4 ({meta.total_frames} frames at 4 fps), train seeds 0 to 3" in card
    assert "s (the last invocation, which resumed after 4 committed episodes)." in card  # its time is not the whole


def test_bad_input_is_refused_and_loses_nothing(dataset_root, tmp_path):
    before = {p: p.stat().st_mtime_ns for p in dataset_root.rglob("*") if p.is_file()}
    with pytest.raises(SystemExit, match="exists and is not empty"):
        collect(dataset_root)
    assert before == {p: p.stat().st_mtime_ns for p in dataset_root.rglob("*") if p.is_file()}
    for bad, message in [("--episodes=0", "--episodes must be >= 1"),
                         ("--episodes=-3", "--episodes must be >= 1"),
                         ("--keep=some", "--keep must be one of"),
                         ("--seed=1000000000", "train seed"),
                         ("--repo_id=noslash", "<org>/<name>")]:
        with pytest.raises(SystemExit, match=message):
            collect_main([bad, f"--root={tmp_path / 'new'}"])
    with pytest.raises(SystemExit, match="different settings"):
        collect(dataset_root, "--resume=true", "--keep=success")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("not a dataset")
    with pytest.raises(SystemExit, match="no dataset to resume"):
        collect(tmp_path / "other", "--resume=true")
    # a mistyped --root: --overwrite deletes a dataset or an empty directory only, and a file is no --root
    with pytest.raises(SystemExit, match=r"--overwrite: .*other is not a LeRobotDataset \(no meta/info.json\)"):
        collect(tmp_path / "other", "--overwrite=true")
    assert (tmp_path / "other" / "notes.txt").read_text() == "not a dataset"
    with pytest.raises(SystemExit, match=r"^error: --root=.*notes.txt is a file, not a dataset directory"):
        collect(tmp_path / "other" / "notes.txt")
    (tmp_path / "empty").mkdir()
    collect(tmp_path / "empty", "--overwrite=true", episodes=2, batch_size=2)
    collect(tmp_path / "empty", "--overwrite=true", "--seed=5", episodes=2, batch_size=2)
    assert [LeRobotDataset(REPO, root=tmp_path / "empty").meta.episodes[i]["seed"] for i in range(2)] == [5, 6]


def test_blocks_past_chunks_size_go_to_the_next_chunk_and_load_in_order(dataset_root, tmp_path, monkeypatch):
    """Blocks are laid out as lerobot v3.0 lays out its files (its own ``update_chunk_file_indices``):
    ``chunks_size`` files to a chunk directory, then the next, and each episode's ``data/`` and
    ``meta/episodes/`` chunk and file indices say where it lies. Every block in chunk-000 would put
    file-1000 before file-101 in the loader's name order and misalign the rows; 3 files a chunk
    stand in for lerobot's 1,000 here. A resume finds the blocks across chunks too."""
    import lerobot.datasets.feature_utils as feature_utils
    import pyarrow.parquet as pq
    from lerobot.datasets.utils import DEFAULT_DATA_PATH, DEFAULT_EPISODES_PATH, update_chunk_file_indices

    from lerobot_crowdnav.data import fast_loader

    monkeypatch.setattr(feature_utils, "DEFAULT_CHUNK_SIZE", 3)
    root = tmp_path / "chunks"
    collect(root, episodes=4, batch_size=1)
    collect(root, "--resume=true", episodes=8, batch_size=1)  # one episode a block: 8 blocks
    assert json.loads((root / "meta/info.json").read_text())["chunks_size"] == 3
    where = [(0, 0)]
    for _ in range(7):
        where.append(update_chunk_file_indices(*where[-1], 3))
    for pattern in (DEFAULT_DATA_PATH, DEFAULT_EPISODES_PATH):
        files = [root / pattern.format(chunk_index=c, file_index=f) for c, f in where]
        assert sorted(root.glob(pattern.split("/chunk-")[0] + "/*/*.parquet")) == files

    ds = LeRobotDataset(REPO, root=root)
    episodes = ds.meta.episodes
    assert [(episodes[e]["data/chunk_index"], episodes[e]["data/file_index"]) for e in range(8)] == where
    assert [(episodes[e]["meta/episodes/chunk_index"], episodes[e]["meta/episodes/file_index"]) for e in range(8)] == where
    for e in range(8):  # the file that the episode's indices name holds its rows
        rows = pq.read_table(root / ds.meta.get_data_file_path(e), columns=["episode_index"])
        assert set(rows["episode_index"].to_pylist()) == {e}
    assert [episodes[e]["seed"] for e in range(8)] == list(range(8))
    np.testing.assert_array_equal(np.asarray(ds.hf_dataset["index"]), np.arange(len(ds)))
    # the rows of an uninterrupted collection in blocks of 8, one chunk: the same seeds, the same frames
    same = LeRobotDataset(REPO, root=dataset_root).hf_dataset.select(range(len(ds)))
    for key in ("observation.state", "action", "episode_index", "frame_index"):
        np.testing.assert_array_equal(np.asarray(ds.hf_dataset[key]), np.asarray(same[key]))
    was = fast_loader.is_installed()
    try:
        assert fast_loader.install()
        items = ds.__getitems__(list(range(len(ds))))
        assert [int(item["index"]) for item in items] == list(range(len(ds)))
        np.testing.assert_array_equal(torch.stack([item["observation.state"] for item in items]).numpy(),
                                      np.asarray(same["observation.state"]))
    finally:
        fast_loader.install() if was else fast_loader.uninstall()


def test_hub_dir_round_trip_and_overwrite(dataset_root, tmp_path):
    hub = tmp_path / "hub"
    push_main([f"--root={dataset_root}", f"--repo_id={REPO}", f"--push_to_hub_dir={hub}"])
    repo = hub / "datasets" / "local" / "test_orca"
    files = sorted(str(p.relative_to(repo)) for p in repo.rglob("*") if p.is_file())
    assert "README.md" in files and "meta/info.json" in files and "meta/stats.json" in files
    assert all(f.split("/")[0] in ("README.md", "meta", "data") for f in files)
    card = (repo / "README.md").read_text()
    assert card.startswith("---\n") and "robotics" in card and "action_is_pad" in card
    assert "BoundedCrowdNav-v0" in card and "seeds 0 to 23" in card
    src, dst = LeRobotDataset(REPO, root=dataset_root), LeRobotDataset(REPO, root=repo)
    for key in ("observation.state", "action", "next.reward"):
        np.testing.assert_array_equal(np.asarray(src.hf_dataset[key]), np.asarray(dst.hf_dataset[key]))
    with pytest.raises(SystemExit, match="--overwrite"):
        push_main([f"--root={dataset_root}", f"--repo_id={REPO}", f"--push_to_hub_dir={hub}"])
    (repo / "stale.txt").write_text("from an older push")
    push_main([f"--root={dataset_root}", f"--repo_id={REPO}", f"--push_to_hub_dir={hub}", "--overwrite=true"])
    assert not (repo / "stale.txt").exists()
    assert sorted(p.name for p in repo.parent.iterdir()) == ["test_orca"]  # no staging left behind


@pytest.mark.parametrize("typ", [pa.float64(), pa.int64(), pa.bool_(), pa.float32()])
def test_episode_stats_read_back_as_numpy_rows_equal_the_python_path(typ):
    """The statistics of a committed block are read as rows of one numpy array; each row equals
    ``np.array(<its python list>)``, values, dtype and shape, across chunks; other column types
    (float32 leaves, ragged or nested lists) take the Python path."""
    from lerobot_crowdnav.data.dataset import _list_rows

    rng = np.random.default_rng(0)
    rows = rng.normal(0, 10, (7, 3))
    values = (rows > 0 if typ == pa.bool_() else rows.astype(np.int64) if typ == pa.int64() else rows).tolist()
    column = pa.chunked_array([pa.array(values[:4], pa.list_(typ)), pa.array(values[4:], pa.list_(typ))])
    for other in (column, pa.chunked_array([pa.array([[1.0], [2.0, 3.0]])]), pa.chunked_array([pa.array([[[1.0]]])])):
        want = [np.array(v) for v in other.to_pylist()]
        got = _list_rows(other)
        assert len(got) == len(want)
        for g, w in zip(got, want, strict=True):
            assert g.dtype == w.dtype and g.shape == w.shape and np.array_equal(g, w)
