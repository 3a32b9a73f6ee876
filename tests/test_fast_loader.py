"""The exact fast ``LeRobotDataset`` reads of ``lerobot_crowdnav.data.fast_loader``: whole items equal to
lerobot's own path (padding, episode filtering, chunk boundaries, dtypes), the guards, the opt-out,
and the stock lerobot-train start-up (plugin loading, spawned DataLoader workers) installing it."""

from __future__ import annotations

import itertools
import os
import pickle
import subprocess
import sys
import textwrap
from contextlib import contextmanager

import lerobot
import numpy as np
import pyarrow as pa
import pytest
import torch
from lerobot.datasets.dataset_reader import DatasetReader
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_crowdnav.data import fast_loader
from lerobot_crowdnav.data.collect import main as collect_main

REPO = "local/test_fast_loader"
CHUNK = {"action": [k / 4 for k in range(5)]}  # PDPO's action chunk
# Past and future windows on several keys (scalars, a bool, the state): padding at both ends.
WINDOWS = {"action": [-0.5, 0.0, 0.25, 1.0], "observation.state": [-0.25, 0.0],
           "next.reward": [0.0, 0.25, 0.5], "next.done": [-0.25, 0.0, 0.25]}


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("fast_loader") / "ds"
    collect_main(["--episodes=16", "--batch_size=8", f"--root={root}", f"--repo_id={REPO}"])
    return root


@pytest.fixture(autouse=True)
def _restore_patch_state():
    was = fast_loader.is_installed()
    yield
    fast_loader.install() if was else fast_loader.uninstall()


@contextmanager
def patched(on: bool):
    fast_loader.install() if on else fast_loader.uninstall()
    assert fast_loader.is_installed() == on
    yield


def assert_items_equal(a: dict, b: dict, where=""):
    assert list(a) == list(b), where
    for key, x in a.items():
        y = b[key]
        if isinstance(x, torch.Tensor):
            assert isinstance(y, torch.Tensor), (where, key)
            assert x.dtype == y.dtype and x.shape == y.shape and torch.equal(x, y), (where, key, x, y)
        else:
            assert type(x) is type(y) and x == y, (where, key)


def episode_edges(ds) -> list[int]:
    """Relative indices at and next to every episode start and end."""
    episode = ds.hf_dataset.data.column("episode_index").to_numpy()
    starts = [0, *(np.flatnonzero(np.diff(episode)) + 1).tolist(), len(episode)]
    edges = {i for s in starts for i in (s - 2, s - 1, s, s + 1)}
    return sorted(i for i in edges if 0 <= i < len(ds))


def compare(ds, indices):
    with patched(False):
        reference = [ds[i] for i in indices]
    with patched(True):
        for i, ref in zip(indices, reference, strict=True):
            assert_items_equal(ds[i], ref, where=i)
    cache = ds.reader.__dict__[fast_loader._CACHE_ATTR]  # and the fast path did serve them
    assert cache.dataset is ds.hf_dataset and cache.every_column is not None


@pytest.mark.parametrize("delta_timestamps", [CHUNK, WINDOWS, None], ids=["chunk", "windows", "no_delta"])
def test_items_equal_lerobot_everywhere(dataset_root, delta_timestamps):
    ds = LeRobotDataset(REPO, root=dataset_root, delta_timestamps=delta_timestamps)
    assert ds.hf_dataset.data.column("action").num_chunks >= 2  # the gather crosses Arrow chunks
    edges = episode_edges(ds)
    indices = edges + list(np.random.default_rng(0).integers(0, len(ds), 300)) + list(range(0, len(ds), 7))
    indices = [int(i) for i in indices]
    compare(ds, indices)
    if delta_timestamps is not None:  # padding really happens at the edges that were compared
        pad = [k for k in ds[edges[0]] if k.endswith("_is_pad")]
        assert any(ds[i][k].any() for i in edges for k in pad)


def test_items_equal_lerobot_on_an_episode_filtered_dataset(dataset_root):
    ds = LeRobotDataset(REPO, root=dataset_root, episodes=[1, 3], delta_timestamps=WINDOWS)
    assert ds.reader._absolute_to_relative_idx is not None and ds.num_episodes == 2
    compare(ds, list(range(len(ds))))
    with patched(True):
        assert set(ds[0]["episode_index"].reshape(-1).tolist()) == {1}
        assert int(ds[len(ds) - 1]["episode_index"]) == 3


@pytest.mark.parametrize("contiguous", [True, False], ids=["contiguous_copies", "chunk_views"])
@pytest.mark.parametrize("delta_timestamps", [CHUNK, WINDOWS, None], ids=["chunk", "windows", "no_delta"])
def test_batches_equal_lerobot_item_by_item(dataset_root, delta_timestamps, contiguous, monkeypatch):
    """``LeRobotDataset.__getitems__`` (what the DataLoader calls with a batch of indices) gives
    lerobot's own items, whether a column is one contiguous copy or read across its Arrow chunks."""
    if not contiguous:
        monkeypatch.setattr(fast_loader, "CONTIGUOUS_BYTES", 0)
    ds = LeRobotDataset(REPO, root=dataset_root, delta_timestamps=delta_timestamps)
    edges = episode_edges(ds)
    rng = np.random.default_rng(1)
    batches = [edges, rng.integers(0, len(ds), 128).tolist(), [5, 5, 0], [len(ds) - 1]]
    with patched(False):
        assert "__getitems__" not in LeRobotDataset.__dict__
        reference = [[ds[i] for i in batch] for batch in batches]
    with patched(True):
        for batch, ref in zip(batches, reference, strict=True):
            assert fast_loader._batch_items(ds.reader, batch) is not None  # the batched path serves it
            got = ds.__getitems__(batch)
            assert len(got) == len(ref)
            for i, item, want in zip(batch, got, ref, strict=True):
                assert_items_equal(item, want, where=i)
        chunks = len(ds.reader.__dict__[fast_loader._CACHE_ATTR].column("action").chunks)
        assert (chunks == 1) if contiguous else (chunks >= 2)


def test_a_dataloader_batch_is_lerobots_batch(dataset_root, monkeypatch):
    ds = LeRobotDataset(REPO, root=dataset_root, delta_timestamps=CHUNK)
    calls = []
    batch_items = fast_loader._batch_items
    monkeypatch.setattr(fast_loader, "_batch_items", lambda reader, idx: calls.append(len(idx)) or batch_items(reader, idx))

    def first_batches(on: bool) -> list[dict]:
        with patched(on):
            loader = torch.utils.data.DataLoader(ds, batch_size=32, shuffle=True,
                                                 generator=torch.Generator().manual_seed(0))
            return list(itertools.islice(loader, 3))

    reference, fast = first_batches(False), first_batches(True)
    assert calls == [32, 32, 32]  # one batched read per batch, none item by item
    for want, got in zip(reference, fast, strict=True):
        assert_items_equal(got, want)


def test_batches_the_fast_path_cannot_serve_are_lerobots(dataset_root):
    filtered = LeRobotDataset(REPO, root=dataset_root, episodes=[1, 3], delta_timestamps=WINDOWS)
    ds = LeRobotDataset(REPO, root=dataset_root, delta_timestamps=CHUNK)
    with patched(False):
        reference = [filtered[i] for i in range(len(filtered))]
    with patched(True):
        assert fast_loader._batch_items(filtered.reader, list(range(len(filtered)))) is None
        for item, want in zip(filtered.__getitems__(list(range(len(filtered)))), reference, strict=True):
            assert_items_equal(item, want)
        with pytest.raises(IndexError):  # lerobot's own error, from its own path
            ds.__getitems__([0, len(ds)])
        assert_items_equal(ds.__getitems__([-1])[0], ds[len(ds) - 1])


def test_items_follow_the_torch_default_dtype_like_lerobot(dataset_root):
    ds = LeRobotDataset(REPO, root=dataset_root, delta_timestamps=CHUNK)
    default = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        compare(ds, [0, 5, len(ds) - 1])
        with patched(True):
            assert ds[5]["action"].dtype == torch.float64
    finally:
        torch.set_default_dtype(default)


def test_the_fallbacks_are_lerobot(dataset_root):
    ds = LeRobotDataset(REPO, root=dataset_root, delta_timestamps=CHUNK)
    with patched(True):
        for bad in (len(ds), 10**9):  # same error as lerobot
            with pytest.raises(IndexError):
                ds[bad]
        assert_items_equal(ds[-1], ds[len(ds) - 1])  # negative index: lerobot's own path
        # Another format on the hf dataset: the fast path steps aside entirely.
        fast = ds[5]
        ds.hf_dataset.set_transform(lambda batch: {k: [torch.tensor(v) for v in vs] for k, vs in batch.items()})
        assert fast_loader._reader_cache(ds.reader) is None
        other = ds[5]
        assert torch.equal(other["action"], fast["action"]) and other["task"] == fast["task"]


def test_a_pickled_reader_installs_the_fast_path_where_it_is_unpickled(dataset_root):
    ds = LeRobotDataset(REPO, root=dataset_root, delta_timestamps=CHUNK)
    with patched(True):
        item = ds[3]
        data = pickle.dumps(ds)
        assert len(data) < 200_000  # the cache does not travel
    fast_loader.uninstall()
    copy = pickle.loads(data)  # what a spawned DataLoader worker does
    assert fast_loader.is_installed()
    assert_items_equal(copy[3], item)
    # Pickled while not installed (a leftover cache in the reader): nothing gets installed.
    fast_loader.uninstall()
    pickle.loads(pickle.dumps(copy))
    assert not fast_loader.is_installed()


def _chunked(values: list, typ: pa.DataType, sizes: list[int]) -> pa.ChunkedArray:
    """Many small chunks, some of them slices (non-zero offsets), some empty."""
    full = pa.array(values, type=typ)
    chunks, start = [], 0
    for n in sizes:
        chunks.append(pa.concat_arrays([full.slice(0, 1), full.slice(start, n)]).slice(1, n))
        start += n
    return pa.chunked_array(chunks, type=typ)


@pytest.mark.parametrize("typ", [pa.float32(), pa.float64(), pa.float16(), pa.int32(), pa.int64(), pa.uint8(),
                                 pa.bool_(), pa.list_(pa.float32(), 3), pa.list_(pa.list_(pa.int16(), 2), 2),
                                 pa.list_(pa.bool_(), 4)])
def test_column_gather_matches_torch_tensor_of_python_values(typ):
    rng = np.random.default_rng(0)
    n, sizes = 60, [7, 0, 13, 1, 20, 19]
    shape, leaf = [], typ
    while pa.types.is_fixed_size_list(leaf):
        shape.append(leaf.list_size)
        leaf = leaf.value_type
    raw = rng.normal(0, 100, (n, *shape))
    if pa.types.is_boolean(leaf):
        raw = raw > 0
    elif pa.types.is_integer(leaf):
        raw = np.abs(raw).astype(np.int64) % 250
    values = raw.tolist()
    col = fast_loader._Column.build(_chunked(values, typ, sizes))
    assert col is not None
    for rows in ([0], [6, 7, 8], [19, 20, 21, 40, 41], [59, 0, 33], list(range(n))):
        want = torch.stack([torch.tensor(pa.array(values, type=typ)[i].as_py()) for i in rows])
        got = col.gather(rows)
        assert got.dtype == want.dtype and got.shape == want.shape and torch.equal(got, want), rows
    for i in (0, 7, 20, 59):
        want = torch.tensor(pa.array(values, type=typ)[i].as_py())
        got = col.row(i)
        assert got.dtype == want.dtype and got.shape == want.shape and torch.equal(got, want), i


def test_unsupported_columns_are_left_to_lerobot():
    assert fast_loader._Column.build(pa.chunked_array([pa.array(["a", "b"])])) is None
    assert fast_loader._Column.build(pa.chunked_array([pa.array([1.0, None])])) is None
    assert fast_loader._Column.build(pa.chunked_array([pa.array([[1.0], [2.0, 3.0]])])) is None  # ragged
    assert fast_loader._Column.build(pa.chunked_array([pa.array([1, 2], type=pa.uint64())])) is None


def test_install_is_idempotent_reversible_and_guarded(monkeypatch):
    originals = {n: DatasetReader.__dict__[n] for n in ("get_item", "_query_hf_dataset", "_get_query_indices")}
    fast_loader.install()
    fast_loader.uninstall()
    assert not fast_loader.is_installed() and "__getstate__" not in DatasetReader.__dict__
    assert "__getitems__" not in LeRobotDataset.__dict__
    assert {n: DatasetReader.__dict__[n] for n in originals} == {n: fast_loader.ORIGINALS[n] for n in originals}
    assert all(f.__module__ == "lerobot.datasets.dataset_reader" for f in fast_loader.ORIGINALS.values())
    assert fast_loader.install() and fast_loader.install() and fast_loader.is_installed()
    fast_loader.uninstall()
    monkeypatch.setattr(lerobot, "__version__", "0.7.0")
    assert not fast_loader.install() and not fast_loader.is_installed()
    monkeypatch.setattr(lerobot, "__version__", "0.6.1")
    monkeypatch.setenv(fast_loader.ENV_VAR, "0")
    assert not fast_loader.install() and not fast_loader.is_installed()
    monkeypatch.delenv(fast_loader.ENV_VAR)
    # A lerobot whose LeRobotDataset reads batches itself: left alone, nothing patched.
    monkeypatch.setattr(LeRobotDataset, "__getitems__", lambda self, indices: [self[i] for i in indices], raising=False)
    assert not fast_loader.install() and not fast_loader.is_installed()
    assert DatasetReader.__dict__["get_item"] is fast_loader.ORIGINALS["get_item"]


def test_loading_the_plugins_leaves_lerobot_untouched():
    """Opt-in: lerobot's plugin discovery (env and policy plugins) patches nothing."""
    code = ("from lerobot.utils.import_utils import register_third_party_plugins; register_third_party_plugins(); "
            "from lerobot.envs.configs import EnvConfig; from lerobot.configs.policies import PreTrainedConfig; "
            "from lerobot.datasets.dataset_reader import DatasetReader; "
            "from lerobot.datasets.lerobot_dataset import LeRobotDataset; "
            "from lerobot_crowdnav.data import fast_loader; "
            "names = ('get_item', '_query_hf_dataset', '_get_query_indices'); "
            "print(EnvConfig.get_choice_class('crowdnav').__name__, PreTrainedConfig.get_choice_class('pdpo').__name__, "
            "fast_loader.is_installed(), "
            "all(DatasetReader.__dict__[n].__module__ == 'lerobot.datasets.dataset_reader' for n in names), "
            "'__getstate__' in DatasetReader.__dict__ or '__getitems__' in LeRobotDataset.__dict__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split()[-5:] == ["CrowdNavEnvConfig", "PDPOConfig", "False", "True", "False"]


TRAIN_SCRIPT = '''
import sys
from torch.utils.data import DataLoader, default_collate


def probe(batch):  # runs in the DataLoader worker
    from lerobot_crowdnav.data import fast_loader
    return default_collate(batch), fast_loader.is_installed()


if __name__ == "__main__":
    root, out = sys.argv[1:3]
    from lerobot_crowdnav.data import fast_loader  # importing it installs nothing
    print("BEFORE", fast_loader.is_installed())
    from lerobot.scripts.lerobot_train import main  # what the lerobot-train console script runs
    sys.argv = ["lerobot-train", "--policy.type=pdpo", "--dataset.repo_id=REPO", f"--dataset.root={root}",
                "--policy.push_to_hub=false", f"--output_dir={out}", "--steps=2", "--batch_size=16",
                "--save_freq=2", "--log_freq=1", "--num_workers=0", "--policy.device=cpu", "--wandb.enable=false"]
    main()
    print("AFTER_TRAIN", fast_loader.is_installed())
    # lerobot-train's workers are spawned: they import no plugin, the pickled reader installs it.
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    ds = LeRobotDataset("REPO", root=root, delta_timestamps={"action": [0, 0.25, 0.5, 0.75, 1.0]})
    loader = DataLoader(ds, batch_size=4, num_workers=1, multiprocessing_context="spawn", collate_fn=probe)
    batch, in_worker = next(iter(loader))
    print("SPAWNED_WORKER", in_worker, tuple(batch["action"].shape))
'''


def test_stock_lerobot_train_runs_with_the_fast_loader(dataset_root, tmp_path):
    script = tmp_path / "train_probe.py"
    script.write_text(textwrap.dedent(TRAIN_SCRIPT).replace("REPO", REPO))
    out = subprocess.run([sys.executable, str(script), str(dataset_root), str(tmp_path / "train")],
                         capture_output=True, text=True, timeout=400, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    lines = dict(line.split(" ", 1) for line in out.stdout.splitlines()
                 if line.startswith(("BEFORE ", "AFTER_TRAIN ", "SPAWNED_WORKER ")))
    assert lines["BEFORE"] == "False" and lines["AFTER_TRAIN"] == "True", out.stdout
    assert (out.stdout + out.stderr).count("fast LeRobotDataset reads active") == 1  # one INFO line
    assert lines["SPAWNED_WORKER"] == "True (4, 5, 2)", out.stdout
    assert (tmp_path / "train" / "checkpoints" / "000002" / "pretrained_model" / "model.safetensors").exists()
