"""ORCA demonstrations as a LeRobotDataset (format v3.0, state only), and the hub-format directory.

Data contract (one frame per control step, fps 4, dt = 0.25 s):

==================  ==============  ==========================================================
observation.state   float32 (269,)  the observation *before* the step (docs/simulator.md), named
action              float32 (2,)    the executed, clipped world-frame velocity (vx, vy), m/s
next.reward         float32         the step's reward
next.done           bool            the step ends the episode (success, collision or timeout)
next.success        bool            the step ends it by reaching the goal
==================  ==============  ==========================================================

plus lerobot's ``timestamp``, ``frame_index``, ``episode_index``, ``index``, ``task_index``.
Episode metadata (``meta/episodes``) also holds the episode ``seed`` and its ``event``.

Action chunks are not stored: a policy asks lerobot for them through delta timestamps
(``action_delta_indices = range(H)``), which returns actions t..t+H-1 of the same episode with
``action_is_pad`` set past its end.

Writing goes around lerobot's per-episode ``save_episode`` (about 0.1 s an episode here: stats with
quantiles per episode, a JSON rewrite per episode): episodes are written in blocks, one data file
and one episodes file per block, with the per-episode statistics computed by numpy and aggregated
over every episode by lerobot's own ``aggregate_feature_stats``, one feature at a time, read back
from the committed episodes files (a DAgger round makes each labelled state an episode: holding
every episode's statistics in memory took gigabytes). Each block is committed by atomic renames (data, episodes,
stats, info last), so a killed collection leaves the blocks already committed, which load.
Block files lie where lerobot v3.0 puts its own: ``chunks_size`` files to a chunk directory, then
the next chunk, so that their names sort in block order.
"""

from __future__ import annotations

import itertools
import json
import shutil
import signal
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from lerobot.datasets.compute_stats import aggregate_feature_stats
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
from lerobot.datasets.feature_utils import get_hf_features_from_features
from lerobot.datasets.io_utils import load_info, write_info, write_stats
from lerobot.datasets.utils import DEFAULT_EPISODES_PATH

from .. import fault
from ..sim.config import CrowdSimConfig
from ..layout import ROBOT_DIM
from ..sim.engine import EVENT_NAMES

FPS = 4
TASK = "Navigate to the goal through the crowd."
STAT_QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
COLLECTION_FILE = "meta/crowdnav_collection.json"  # what was collected, for --resume checks
CARD_FILE = "README.md"  # the dataset card, written last: its presence marks a complete collection


def collection_complete(root: str | Path) -> bool:
    """Whether collect_orca.py finished ``root``: it writes the card last, so a killed one has none."""
    return (Path(root) / CARD_FILE).exists()


def observation_names(cfg: CrowdSimConfig) -> list[str]:
    """Column names of ``observation.state`` (positions relative to the robot, world axes)."""
    names = ["robot_px", "robot_py", "robot_radius", "goal_x", "goal_y", "robot_v_pref", "robot_theta",
             "robot_vx", "robot_vy"]
    for i in range(cfg.num_humans):
        for k in range(cfg.prediction_steps + 1):
            names += [f"human{i:02d}_x{k}", f"human{i:02d}_y{k}"]
    names += [f"human{i:02d}_visible" for i in range(cfg.num_humans)]
    assert len(names) == cfg.obs_dim and ROBOT_DIM == 7
    return names


def features(cfg: CrowdSimConfig) -> dict:
    return {
        "observation.state": {"dtype": "float32", "shape": (cfg.obs_dim,), "names": observation_names(cfg)},
        "action": {"dtype": "float32", "shape": (2,), "names": ["vx", "vy"]},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
    }


def block_location(n: int, chunks_size: int) -> dict[str, int]:
    """``chunk_index`` and ``file_index`` of the n-th block (from 0): where lerobot's own writer puts
    its n-th file (``update_chunk_file_indices`` from chunk 0, file 0). lerobot's loader reads
    ``*/*.parquet`` in name order: with at most 1,000 three-digit files a chunk, block order."""
    chunk, file = divmod(n, chunks_size)
    return {"chunk_index": chunk, "file_index": file}


def committed_episodes_files(root: Path, info) -> list[Path]:
    """The episodes files of the committed blocks of the dataset at ``root``, in order; ``info``:
    its ``meta/info.json``. Reads only."""
    out, total = [], 0
    for n in itertools.count():
        f = root / DEFAULT_EPISODES_PATH.format(**block_location(n, info.chunks_size))
        if not f.exists():
            break
        total += pq.read_metadata(f).num_rows
        if total > info.total_episodes:
            break  # renamed but not recorded in info.json: not committed
        out.append(f)
    return out


def _episode_stats(columns: dict[str, np.ndarray], bounds: np.ndarray) -> list[dict]:
    """lerobot's per-episode statistics (min, max, mean, std, count, q01..q99) for each feature,
    one dict per episode; ``bounds`` are the frame offsets of the episodes."""
    out = [{} for _ in range(len(bounds) - 1)]
    for key, values in columns.items():
        x = values.astype(np.float64).reshape(len(values), -1)
        for e, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
            seg = x[lo:hi]
            stats = {"min": seg.min(0), "max": seg.max(0), "mean": seg.mean(0), "std": seg.std(0),
                     "count": np.array([hi - lo])}
            for name, q in zip(STAT_QUANTILES, np.quantile(seg, list(STAT_QUANTILES.values()), axis=0),
                               strict=True):
                stats[name] = q
            out[e][key] = stats
    return out


@contextmanager
def _no_interrupt():
    """Defer Ctrl-C / SIGTERM until a block is committed, then raise it."""
    received = []
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        for s in handlers:
            signal.signal(s, lambda sig, _frame: received.append(sig))
    except ValueError:  # not the main thread: nothing to defer
        handlers = {}
    try:
        yield
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
        if received:
            raise KeyboardInterrupt


class DemonstrationWriter:
    """Appends blocks of whole episodes to a LeRobotDataset directory (v3.0, no videos)."""

    def __init__(self, root: Path, repo_id: str, sim_config: CrowdSimConfig, collection: dict,
                 resume: bool):
        self.root = Path(root)
        self.repo_id = repo_id
        self.features = features(sim_config)
        if resume and (self.root / "meta/info.json").exists():
            self._open_existing(collection)
        else:
            self._create(collection)
        self.hf_features = get_hf_features_from_features(self.info.features)

    def _create(self, collection: dict) -> None:
        """Write the empty dataset (info with its one task, tasks, collection record) aside and
        rename it into place: a kill leaves no root, or a root that resumes."""
        staging = self.root.with_name(f".{self.root.name}.create.tmp")
        shutil.rmtree(staging, ignore_errors=True)
        meta = LeRobotDatasetMetadata.create(self.repo_id, FPS, self.features, root=staging, use_videos=False)
        meta.save_episode_tasks([TASK])
        meta.info.total_tasks = len(meta.tasks)
        write_info(meta.info, staging)
        (staging / COLLECTION_FILE).write_text(json.dumps(collection, indent=2))
        fault.point("collect.create")
        if self.root.exists():
            self.root.rmdir()  # validated empty
        staging.replace(self.root)
        self.info = meta.info
        self.n_files = 0

    def _open_existing(self, collection: dict) -> None:
        path = self.root / COLLECTION_FILE
        if not path.exists():
            raise ValueError(f"{self.root} is not a collection made by collect_orca.py ({COLLECTION_FILE} missing)")
        previous = _flat(json.loads(path.read_text()))
        current = _flat(json.loads(json.dumps(collection)))
        changed = {k: (previous.get(k), v) for k, v in current.items()
                   if k != "episodes" and previous.get(k) != v}
        if changed:
            detail = ", ".join(f"{k}: {a!r} -> {b!r}" for k, (a, b) in changed.items())
            raise ValueError(f"--resume with different settings than the existing collection ({detail})")
        self.info = load_info(self.root)
        files = committed_episodes_files(self.root, self.info)
        found = sum(pq.read_metadata(f).num_rows for f in files)
        if found != self.info.total_episodes:  # the cleanup below would delete the blocks not found
            raise ValueError(f"{self.root}: meta/info.json counts {self.info.total_episodes} episodes, the block "
                             f"files where lerobot v3.0 puts them hold {found}; collect into a new --root")
        self.n_files = len(files)
        # Remove what an interrupted commit may have left beyond the committed blocks.
        for tmp in sorted(self.root.rglob("*.tmp"), reverse=True):
            shutil.rmtree(tmp) if tmp.is_dir() else tmp.unlink()
        committed = {p for n in range(self.n_files) for p in self._block_files(n)}
        for pattern in ("data/*/*.parquet", "meta/episodes/*/*.parquet"):
            for extra in sorted(set(self.root.glob(pattern)) - committed):
                extra.unlink()

    def _block_files(self, n: int) -> tuple[Path, Path]:
        """The data and episodes files of the n-th block."""
        where = block_location(n, self.info.chunks_size)
        return self.root / self.info.data_path.format(**where), self.root / DEFAULT_EPISODES_PATH.format(**where)

    def committed_blocks(self) -> list[list[dict]]:
        """``{episode_index, seed, event, length}`` of each committed block's episodes."""
        return [pq.read_table(f, columns=["episode_index", "seed", "event", "length"]).to_pylist()
                for f in committed_episodes_files(self.root, self.info)]

    def append(self, episodes: list[dict]) -> None:
        """Commit a block of episodes; each is ``{seed, event, obs (T, D), action (T, 2),
        reward (T,), success (bool)}``."""
        if not episodes:
            return
        lengths = np.array([len(e["action"]) for e in episodes])
        bounds = np.concatenate([[0], np.cumsum(lengths)])
        n_frames = int(bounds[-1])
        first_ep = self.info.total_episodes
        first_frame = self.info.total_frames
        episode_index = np.repeat(np.arange(first_ep, first_ep + len(episodes)), lengths)
        frame_index = np.concatenate([np.arange(n) for n in lengths])
        done = np.zeros(n_frames, bool)
        done[bounds[1:] - 1] = True
        success = np.zeros(n_frames, bool)
        success[bounds[1:] - 1] = [e["success"] for e in episodes]
        columns = {
            "observation.state": np.concatenate([e["obs"] for e in episodes]).astype(np.float32),
            "action": np.concatenate([e["action"] for e in episodes]).astype(np.float32),
            "next.reward": np.concatenate([e["reward"] for e in episodes]).astype(np.float32),
            "next.done": done,
            "next.success": success,
            "timestamp": (frame_index / FPS).astype(np.float32),
            "frame_index": frame_index.astype(np.int64),
            "episode_index": episode_index.astype(np.int64),
            "index": np.arange(first_frame, first_frame + n_frames, dtype=np.int64),
            "task_index": np.zeros(n_frames, np.int64),
        }
        ep_stats = _episode_stats(columns, bounds)

        def fixed(x):
            return pa.FixedSizeListArray.from_arrays(pa.array(x.reshape(-1)), x.shape[1])

        arrays = {k: (fixed(v) if v.ndim == 2 else pa.array(v)) for k, v in columns.items()}
        data = pa.table(arrays).cast(self.hf_features.arrow_schema)

        where = block_location(self.n_files, self.info.chunks_size)
        ep_rows = {
            "episode_index": np.arange(first_ep, first_ep + len(episodes)),
            "tasks": [[TASK]] * len(episodes),
            "length": lengths,
            "data/chunk_index": np.full(len(episodes), where["chunk_index"]),
            "data/file_index": np.full(len(episodes), where["file_index"]),
            "dataset_from_index": first_frame + bounds[:-1],
            "dataset_to_index": first_frame + bounds[1:],
            "seed": np.array([e["seed"] for e in episodes], np.int64),
            "event": [e["event"] for e in episodes],
        }
        for key in columns:
            for stat in ep_stats[0][key]:
                ep_rows[f"stats/{key}/{stat}"] = [s[key][stat].tolist() for s in ep_stats]
        ep_rows["meta/episodes/chunk_index"] = np.full(len(episodes), where["chunk_index"])
        ep_rows["meta/episodes/file_index"] = np.full(len(episodes), where["file_index"])
        ep_table = pa.table(ep_rows)

        # Aggregated over all episodes in order, not block by block: the same bits whatever the
        # block boundaries (an interrupted and resumed run ends with an uninterrupted run's stats).
        stats = self._aggregate(ep_stats)
        self.info.total_episodes += len(episodes)
        self.info.total_frames += n_frames
        self.info.splits = {"train": f"0:{self.info.total_episodes}"}

        data_path, ep_path = self._block_files(self.n_files)
        for p in (data_path, ep_path):
            p.parent.mkdir(parents=True, exist_ok=True)
        with _no_interrupt():
            pq.write_table(data, f"{data_path}.tmp", compression="snappy")
            fault.point("collect.data_written")
            pq.write_table(ep_table, f"{ep_path}.tmp", compression="snappy")
            tmp_root = self.root / ".commit.tmp"
            tmp_root.mkdir(exist_ok=True)
            write_stats(stats, tmp_root)
            write_info(self.info, tmp_root)
            Path(f"{data_path}.tmp").replace(data_path)
            Path(f"{ep_path}.tmp").replace(ep_path)
            (tmp_root / "meta/stats.json").replace(self.root / "meta/stats.json")
            fault.point("collect.renaming")
            (tmp_root / "meta/info.json").replace(self.root / "meta/info.json")
            fault.point("collect.committed")
            shutil.rmtree(tmp_root)
        self.n_files += 1

    def _aggregate(self, new: list[dict]) -> dict:
        """lerobot's ``aggregate_stats`` over the committed episodes and ``new``, in order, one
        feature at a time (the same arithmetic on the same stacked values, so the same bits)."""
        files = committed_episodes_files(self.root, self.info)
        return {key: aggregate_feature_stats([*(s for f in files for s in _read_feature_stats(f, key)),
                                              *(s[key] for s in new)])
                for key in new[0]}


def _read_feature_stats(episodes_file: Path, key: str) -> list[dict]:
    """One feature's per-episode statistics from a committed episodes file, as ``_episode_stats``
    made them."""
    prefix = f"stats/{key}/"
    names = [n for n in pq.read_schema(episodes_file).names if n.startswith(prefix)]
    table = pq.read_table(episodes_file, columns=names)
    rows = {name[len(prefix):]: _list_rows(table.column(name)) for name in names}
    return [dict(zip(rows, values)) for values in zip(*rows.values())]


_NUMPY_LEAVES = (pa.float64(), pa.int64(), pa.bool_())  # what np.array(<python values>) gives back


def _list_rows(column: pa.ChunkedArray) -> list[np.ndarray]:
    """``[np.array(v) for v in column.to_pylist()]`` for a column of equal-length lists, as rows of
    one numpy array: a DAgger round's block holds tens of thousands of episodes, and their
    state statistics as Python floats took gigabytes (a main job was killed for memory)."""
    arr = column.combine_chunks()
    if pa.types.is_list(arr.type) and arr.type.value_type in _NUMPY_LEAVES and arr.null_count == 0 and len(arr):
        lengths = arr.value_lengths().to_numpy()
        values = arr.flatten()
        if (lengths == lengths[0]).all() and values.null_count == 0:
            return list(values.to_numpy(zero_copy_only=False).reshape(len(arr), lengths[0]))
    return [np.array(v) for v in column.to_pylist()]


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def outcome_counts(events: list[str]) -> dict[str, int]:
    return {name: sum(e == name for e in events) for name in EVENT_NAMES[1:]}
