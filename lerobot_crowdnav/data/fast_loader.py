"""Exact, faster ``LeRobotDataset.__getitem__`` for state-only datasets (lerobot 0.6.1, datasets 4).

Why this exists: with ``delta_timestamps`` (PDPO's 5-step action chunk) every item calls
``DatasetReader._query_hf_dataset``, which runs ``torch.stack(self.hf_dataset[key][indices])``. In
datasets 4, ``Dataset[column]`` builds a ``Column`` whose constructor reads ``Dataset.features``
twice, and each read is a ``copy.deepcopy`` of the ``Features`` (about 55 % of the time of an item
on our 269-float state); ``Column[indices]`` then formats *every* column of those rows through
``hf_transform_to_torch``, which builds the tensors from Python lists with ``torch.tensor``. The row
itself (``hf_dataset[idx]``) and the episode bounds (``meta.episodes[ep_idx]``, a whole formatted
row) go through the same formatting. On our ORCA dataset that was ~1.3-2.6 ms per item, which made
``lerobot-train --policy.type=pdpo`` loader-bound.

What it does: :func:`install` replaces three ``DatasetReader`` methods (the originals are kept in
:data:`ORIGINALS`; :func:`uninstall` restores them):

* ``_query_hf_dataset``: each queried non-video column of a plain numeric/bool Arrow type (a
  scalar or fixed-size lists of them, no nulls) is gathered from a per-reader, per-process cache of
  the column (``hf_dataset.data.column(key)``) as numpy: views of its memory-mapped Arrow chunks,
  or one contiguous copy of a small column;
* ``get_item``: for readers without video, image transforms or depth, the row comes from the same
  cache and the task name is ``meta.tasks.index[task_idx]`` (what ``meta.tasks.iloc[i].name``
  returns); the rest of the method is lerobot's;
* ``_get_query_indices``: the episode bounds come from cached ``dataset_from_index`` /
  ``dataset_to_index`` arrays;

and gives ``LeRobotDataset`` a ``__getitems__`` (lerobot defines none), which torch's DataLoader
calls with a whole batch of indices: each column, and each action window, is gathered for the
batch in one numpy operation instead of item by item (the items, then collated as before, are the
same), which takes the loader's share of a 128-sample batch from about 12 ms to a few;

and adds ``DatasetReader.__getstate__`` (lerobot defines none) so that a pickled reader carries an
empty cache whose unpickling installs the fast path: lerobot-train's DataLoader workers are
*spawned* by default and import no plugin. Anything the cache cannot reproduce exactly (video
keys, other column types, indices outside the table, an ``hf_dataset`` with another
format/transform or an indices mapping) goes through the original code.

It is exact: the index arithmetic (``_absolute_to_relative_idx`` of an episode-filtered dataset,
the clamping and ``*_is_pad`` masks) is lerobot's, and each tensor has the values, dtype and shape
that ``torch.tensor`` of the Python value gives in the original (floats -> the default dtype,
integers -> int64, bools -> bool), with the same keys in the same order;
``tests/test_fast_loader.py`` compares whole items with ``torch.equal``. The cache holds views of the
large columns (the state) and contiguous copies of the small ones (up to ``CONTIGUOUS_BYTES``: the
scalars and the action, about 50 bytes per frame), in every process, beyond the shared page cache
of the memory-mapped file. It is rebuilt when the reader's
``hf_dataset`` (or its table, or ``meta.episodes``) is replaced.

Where it is active: opt-in, where our datasets are read for training. The PDPO policy plugin
calls :func:`install` from ``PDPOPolicy.get_optim_params``, which lerobot-train calls (fresh or
resumed run) before it builds its DataLoader, so the stock ``lerobot-train --policy.type=pdpo``
gets it with no flag; other policies, other CLIs and importing the env plugin leave lerobot as it
is. Any other script opts in by calling :func:`install`. It logs one INFO line when it becomes
active, only installs on lerobot 0.6.1 whose methods have the expected signatures (otherwise
nothing is patched), and ``LEROBOT_CROWDNAV_FAST_LOADER=0`` opts out.

A candidate upstream fix: the same column cache inside lerobot's ``DatasetReader`` (or a
``Features`` copy that datasets does not deep-copy per column access) would make this module
unnecessary; docs/policy.md has the measurements to file with it.
"""

from __future__ import annotations

import bisect
import inspect
import logging
import os
from typing import Any

import numpy as np
import pyarrow as pa
import torch

ENV_VAR = "LEROBOT_CROWDNAV_FAST_LOADER"
SUPPORTED_LEROBOT_VERSION = "0.6.1"
_CACHE_ATTR = "_crowdnav_fast_loader_cache"
_EPISODES_ATTR = "_crowdnav_fast_loader_episodes"
_MARK = "_crowdnav_fast_loader"

# A column up to this size is copied into one contiguous array (the scalar columns and the
# action: about 50 bytes per frame in all); larger ones (the state) stay views of their Arrow chunks.
CONTIGUOUS_BYTES = 64 << 20

# The methods replaced, as found before install (filled by install()).
ORIGINALS: dict[str, Any] = {}

logger = logging.getLogger(__name__)


def enabled_by_env() -> bool:
    """False when ``LEROBOT_CROWDNAV_FAST_LOADER`` is 0/false/no/off."""
    return os.environ.get(ENV_VAR, "1").strip().lower() not in ("0", "false", "no", "off")


class _Column:
    """A numeric column as zero-copy numpy views of its Arrow chunks, gathered like the original."""

    __slots__ = ("chunks", "starts", "start_list", "kind")

    def __init__(self, chunks: list[np.ndarray], starts: np.ndarray, kind: str):
        self.chunks, self.starts, self.kind = chunks, starts, kind
        self.start_list = starts.tolist()

    @classmethod
    def build(cls, chunked: pa.ChunkedArray) -> _Column | None:
        shape, leaf = [], chunked.type
        while pa.types.is_fixed_size_list(leaf):
            shape.append(leaf.list_size)
            leaf = leaf.value_type
        if pa.types.is_floating(leaf):
            kind = "float"
        elif pa.types.is_boolean(leaf):
            kind = "bool"
        elif pa.types.is_integer(leaf) and leaf != pa.uint64():  # uint64 may not fit in int64
            kind = "int"
        else:
            return None
        if 0 in shape:
            return None
        chunks, starts, start = [], [], 0
        for chunk in chunked.chunks:
            n = len(chunk)
            if n == 0:
                continue
            values = chunk
            for _ in shape:
                if values.null_count:
                    return None
                values = values.flatten()  # respects the chunk's offset and length
            if values.null_count:
                return None
            array = values.to_numpy(zero_copy_only=False)  # a view for numbers, a copy for bools
            chunks.append(array.reshape(n, *shape))
            starts.append(start)
            start += n
        if len(chunks) > 1 and sum(c.nbytes for c in chunks) <= CONTIGUOUS_BYTES:
            chunks, starts = [np.concatenate(chunks)], [0]  # one gather for a whole batch
        return cls(chunks, np.asarray(starts, dtype=np.int64), kind)

    def _to_torch(self, out: np.ndarray) -> torch.Tensor:
        tensor = torch.from_numpy(out)
        # torch.tensor(<python values>) of the original: floats -> default dtype, ints -> int64.
        if self.kind == "float":
            return tensor.to(torch.get_default_dtype())
        if self.kind == "int":
            return tensor.to(torch.int64)
        return tensor

    def row(self, i: int) -> torch.Tensor:
        """Row ``i`` as ``torch.tensor(<its python value>)`` would give it (0-d for scalars)."""
        c = bisect.bisect_right(self.start_list, i) - 1
        chunk = self.chunks[c]
        out = chunk[[i - self.start_list[c]]]  # fancy indexing: a fresh copy, shape (1, ...)
        return self._to_torch(out.reshape(chunk.shape[1:]))

    def gather(self, rows) -> torch.Tensor:
        """Rows ``rows`` (a list or an int array of any shape) stacked: shape ``(*rows.shape, ...)``."""
        idx = np.asarray(rows, dtype=np.int64)
        flat = idx.reshape(-1)
        which = np.searchsorted(self.starts, flat, side="right") - 1
        first = int(which[0])
        if (which == first).all():
            out = self.chunks[first][flat - self.starts[first]]  # fancy indexing: a fresh copy
        else:  # a view per row: cheaper than a pass per chunk when the rows are spread over many
            chunks, offsets = self.chunks, (flat - self.starts[which]).tolist()
            out = np.stack([chunks[c][i] for c, i in zip(which.tolist(), offsets)])
        return self._to_torch(out.reshape(*idx.shape, *out.shape[1:]))


class _ReaderCache:
    """Columns of one ``hf_dataset`` (identity-checked); pickles/deep-copies to an empty cache."""

    def __init__(self, dataset=None):
        self.dataset = dataset
        self.table = dataset._data if dataset is not None else None
        self.columns: dict[str, _Column | None] = {}
        self.every_column: list[tuple[str, _Column]] | None = None
        self.every_column_done = False
        self.bounds = None

    def __reduce__(self):
        return (_ReaderCache, ())

    def column(self, key: str) -> _Column | None:
        try:
            return self.columns[key]
        except KeyError:
            pass
        col = None
        if key in self.table.column_names:
            try:
                col = _Column.build(self.table.column(key))
            except (pa.ArrowException, ValueError, TypeError) as e:  # pragma: no cover - defensive
                logger.debug("fast loader: column %s not cached (%s)", key, e)
        self.columns[key] = col
        return col

    def all_columns(self) -> list[tuple[str, _Column]] | None:
        """Every column of the table in its order, or None if one of them is not cached."""
        if not self.every_column_done:
            cols = [(name, self.column(name)) for name in self.table.column_names]
            self.every_column = None if any(col is None for _, col in cols) else cols
            self.every_column_done = True
        return self.every_column

    def row(self, idx: Any) -> dict | None:
        """``hf_dataset[idx]`` (all columns, in table order), or None where it must not be used."""
        if type(idx) is not int or not 0 <= idx < self.table.num_rows:
            return None
        cols = self.all_columns()
        return None if cols is None else {name: col.row(idx) for name, col in cols}


def _reader_cache(reader) -> _ReaderCache | None:
    """The reader's column cache, or None where the fast path would not be exact."""
    from lerobot.datasets import dataset_reader

    ds = reader.hf_dataset
    if (ds is None or ds._indices is not None or ds._format_type != "custom"
            or ds._format_columns is not None
            or ds._format_kwargs.get("transform") is not dataset_reader.hf_transform_to_torch):
        return None
    cache = reader.__dict__.get(_CACHE_ATTR)
    if cache is None or cache.dataset is not ds or cache.table is not ds._data:
        cache = _ReaderCache(ds)
        reader.__dict__[_CACHE_ATTR] = cache
    return cache


def _is_index(i: Any, n: int) -> bool:
    return isinstance(i, (int, np.integer)) and not isinstance(i, bool) and 0 <= i < n


def _fast_query_hf_dataset(self, query_indices: dict[str, list[int]]) -> dict:
    """Drop-in for ``DatasetReader._query_hf_dataset`` (same result; see the module docstring)."""
    original = ORIGINALS["_query_hf_dataset"]
    cache = _reader_cache(self)
    if cache is None:
        return original(self, query_indices)
    result: dict = {}
    video_keys = self._meta.video_keys
    n_rows = cache.table.num_rows
    for key, q_idx in query_indices.items():
        if key in video_keys:
            continue
        relative_indices = (
            q_idx
            if self._absolute_to_relative_idx is None
            else [self._absolute_to_relative_idx[idx] for idx in q_idx]
        )
        col = cache.column(key)
        if col is None or len(relative_indices) == 0 or not all(_is_index(i, n_rows) for i in relative_indices):
            result[key] = original(self, {key: q_idx})[key]
        else:
            result[key] = col.gather(relative_indices)
    return result


def _episode_bounds(reader) -> tuple[np.ndarray, np.ndarray] | None:
    """``dataset_from_index`` / ``dataset_to_index`` of ``meta.episodes`` (positional), cached."""
    episodes = reader._meta.episodes
    if episodes is None or episodes._indices is not None or episodes._format_type is not None:
        return None
    cache = reader.__dict__.get(_EPISODES_ATTR)
    if cache is not None and cache.dataset is episodes and cache.table is episodes._data:
        return cache.bounds
    cache = _ReaderCache(episodes)
    bounds = None
    table = episodes._data
    if {"dataset_from_index", "dataset_to_index"} <= set(table.column_names):
        cols = [table.column(k) for k in ("dataset_from_index", "dataset_to_index")]
        if all(pa.types.is_integer(c.type) and c.null_count == 0 for c in cols):
            bounds = tuple(c.to_numpy() for c in cols)
    cache.bounds = bounds
    reader.__dict__[_EPISODES_ATTR] = cache
    return bounds


def _fast_get_query_indices(self, abs_idx: int, ep_idx: int):
    """Drop-in for ``DatasetReader._get_query_indices``: the episode bounds come from a cached
    array instead of formatting the whole ``meta.episodes[ep_idx]`` row; the rest is verbatim."""
    bounds = _episode_bounds(self)
    if bounds is None or not _is_index(ep_idx, len(bounds[0])):
        return ORIGINALS["_get_query_indices"](self, abs_idx, ep_idx)
    ep_start = int(bounds[0][ep_idx])
    ep_end = int(bounds[1][ep_idx])
    query_indices = {
        key: [max(ep_start, min(ep_end - 1, abs_idx + delta)) for delta in delta_idx]
        for key, delta_idx in self.delta_indices.items()
    }
    padding = {
        f"{key}_is_pad": torch.BoolTensor(
            [(abs_idx + delta < ep_start) | (abs_idx + delta >= ep_end) for delta in delta_idx]
        )
        for key, delta_idx in self.delta_indices.items()
    }
    return query_indices, padding


def _fast_get_item(self, idx) -> dict:
    """Drop-in for ``DatasetReader.get_item`` on state-only readers (no video, no image transform,
    no depth): the row comes from the column cache instead of ``hf_dataset[idx]`` and the task
    name is ``meta.tasks.index[task_idx]`` (what ``meta.tasks.iloc[task_idx].name`` returns,
    without building a pandas row). Anything else goes to the original."""
    cache = _reader_cache(self)
    item = None
    if (cache is not None and not self._meta.video_keys and self._image_transforms is None
            and not self._image_depth_units):
        item = cache.row(idx)
    if item is None:
        return ORIGINALS["get_item"](self, idx)
    ep_idx = item["episode_index"].item()
    abs_idx = item["index"].item()

    if self.delta_indices is not None:
        query_indices, padding = self._get_query_indices(abs_idx, ep_idx)
        query_result = self._query_hf_dataset(query_indices)
        item = {**item, **padding}
        for key, val in query_result.items():
            item[key] = val

    task_idx = item["task_index"].item()
    item["task"] = self._meta.tasks.index[task_idx]
    return item


def _batch_items(reader, indices: list) -> list[dict] | None:
    """``[reader.get_item(i) for i in indices]`` gathered a column at a time (one numpy gather per
    column and per action window for the whole batch, instead of one per item), or None where the
    per-item path must serve: video, image transforms or depth, an episode-filtered reader, an index
    or a window row outside the table, a column that is not cached."""
    cache = _reader_cache(reader)
    if (cache is None or reader._meta.video_keys or reader._image_transforms is not None
            or reader._image_depth_units or reader._absolute_to_relative_idx is not None):
        return None
    n_rows = cache.table.num_rows
    cols = cache.all_columns()
    if cols is None or not indices or not all(_is_index(i, n_rows) for i in indices):
        return None
    rows = np.asarray(indices, dtype=np.int64)
    batch = {name: col.gather(rows) for name, col in cols}
    padding = {}
    if reader.delta_indices is not None:
        bounds = _episode_bounds(reader)
        episode = batch["episode_index"].numpy()
        if bounds is None or ((episode < 0) | (episode >= len(bounds[0]))).any():
            return None
        start, end = bounds[0][episode][:, None], bounds[1][episode][:, None]
        absolute = batch["index"].numpy()[:, None]
        for key, deltas in reader.delta_indices.items():
            wanted = absolute + np.asarray(deltas, dtype=np.int64)[None, :]
            padding[f"{key}_is_pad"] = torch.from_numpy((wanted < start) | (wanted >= end))
            window = np.maximum(start, np.minimum(end - 1, wanted))  # lerobot's clamp, verbatim
            col = cache.column(key)
            if col is None or window.size == 0 or window.min() < 0 or window.max() >= n_rows:
                return None
            batch[key] = col.gather(window)
    keys = [*batch, *(k for k in padding if k not in batch)]
    values = [{**batch, **padding}[k].unbind(0) for k in keys]
    tasks = reader._meta.tasks.index
    return [{**dict(zip(keys, item)), "task": tasks[int(t)]}
            for item, t in zip(zip(*values), batch["task_index"].tolist())]


def _fast_getitems(self, indices: list) -> list[dict]:
    """``LeRobotDataset.__getitems__``, which torch's DataLoader calls with a whole batch of indices
    when a dataset has it: the items of :func:`_batch_items` where it applies, else
    ``[self[i] for i in indices]`` (lerobot's own checks and errors)."""
    if self.writer is None or self._is_finalized:
        reader = self._ensure_reader()
        if reader.hf_dataset is not None:
            items = _batch_items(reader, indices)
            if items is not None:
                return items
    return [self[i] for i in indices]


def _unpickled_cache() -> _ReaderCache:
    """What ``_InstallOnUnpickle`` becomes: an empty cache, after installing the fast path in this
    process (a DataLoader worker started with ``spawn``, lerobot-train's default, imports no plugin)."""
    install()
    return _ReaderCache()


class _InstallOnUnpickle:
    def __reduce__(self):
        return (_unpickled_cache, ())


def _reader_getstate(self) -> dict:
    """``DatasetReader.__getstate__`` (it has none of its own): the instance dict, the cache
    replaced by a placeholder that installs the fast path where the reader is unpickled."""
    state = dict(self.__dict__)
    state[_CACHE_ATTR] = _InstallOnUnpickle()
    state.pop(_EPISODES_ATTR, None)
    return state


_PATCHES = {
    "_query_hf_dataset": (_fast_query_hf_dataset, ["self", "query_indices"]),
    "_get_query_indices": (_fast_get_query_indices, ["self", "abs_idx", "ep_idx"]),
    "get_item": (_fast_get_item, ["self", "idx"]),
}
for _fn, _ in _PATCHES.values():
    _fn.__dict__[_MARK] = True
_reader_getstate.__dict__[_MARK] = True
_fast_getitems.__dict__[_MARK] = True


def is_installed() -> bool:
    """Whether lerobot's ``DatasetReader`` currently runs the fast methods (and ``LeRobotDataset``
    the batched read)."""
    from lerobot.datasets.dataset_reader import DatasetReader
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return (all(getattr(DatasetReader.__dict__.get(name), _MARK, False) for name in (*_PATCHES, "__getstate__"))
            and getattr(LeRobotDataset.__dict__.get("__getitems__"), _MARK, False))


def install() -> bool:
    """Patch lerobot's ``DatasetReader`` and add ``LeRobotDataset.__getitems__`` (idempotent).
    Returns whether the fast path is active.

    Does nothing when ``LEROBOT_CROWDNAV_FAST_LOADER=0``, on a lerobot other than 0.6.1, or when
    a method to replace is missing or has another signature (then nothing is patched at all).
    """
    if not enabled_by_env():
        return False
    try:
        import lerobot
        from lerobot.datasets.dataset_reader import DatasetReader
        from lerobot.datasets.lerobot_dataset import LeRobotDataset
    except ImportError:  # pragma: no cover - lerobot is a dependency
        return False
    if getattr(lerobot, "__version__", None) != SUPPORTED_LEROBOT_VERSION:
        logger.debug("fast loader: lerobot %s is not %s, not installed",
                     getattr(lerobot, "__version__", None), SUPPORTED_LEROBOT_VERSION)
        return False
    if is_installed():
        return True
    found = {}
    for name, (_, params) in _PATCHES.items():
        current = DatasetReader.__dict__.get(name)
        if getattr(current, _MARK, False):
            found[name] = ORIGINALS[name]
            continue
        if not inspect.isfunction(current) or list(inspect.signature(current).parameters) != params:
            logger.debug("fast loader: unexpected DatasetReader.%s, not installed", name)
            return False
        found[name] = current
    getstate = DatasetReader.__dict__.get("__getstate__")
    if getstate is not None and not getattr(getstate, _MARK, False):
        logger.debug("fast loader: DatasetReader has its own __getstate__, not installed")
        return False
    getitems = LeRobotDataset.__dict__.get("__getitems__")
    if getitems is not None and not getattr(getitems, _MARK, False):
        logger.debug("fast loader: LeRobotDataset has its own __getitems__, not installed")
        return False
    ORIGINALS.update(found)
    for name, (fast, _) in _PATCHES.items():
        setattr(DatasetReader, name, fast)
    DatasetReader.__getstate__ = _reader_getstate
    LeRobotDataset.__getitems__ = _fast_getitems
    logger.info("fast LeRobotDataset reads active (lerobot_crowdnav.data.fast_loader; %s=0 turns them off)", ENV_VAR)
    return True


def uninstall() -> None:
    """Restore lerobot's original methods (for tests and A/B measurements)."""
    from lerobot.datasets.dataset_reader import DatasetReader
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    for name, (fast, _) in _PATCHES.items():
        if DatasetReader.__dict__.get(name) is fast:
            setattr(DatasetReader, name, ORIGINALS[name])
    if DatasetReader.__dict__.get("__getstate__") is _reader_getstate:
        del DatasetReader.__getstate__  # lerobot defines none: back to object.__getstate__
    if LeRobotDataset.__dict__.get("__getitems__") is _fast_getitems:
        del LeRobotDataset.__getitems__  # lerobot defines none: the DataLoader reads item by item
