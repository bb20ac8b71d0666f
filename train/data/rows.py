"""Rows of a split read from its subject files when a batch needs them, instead of the whole split in memory.

The paper's training split (14,400 images at 512²) is ~75 GB as float32 tensors, more than a GPU machine
spares, so the training stages gather each batch's rows through :class:`train.data.dataset.GazeDataset` (the
one reader: its bounded HDF5 reads, resizing and compositing) and keep only a bounded cache of decoded rows.
A row read here is ``convert(dataset[i])``: exactly the tensors the whole-split loader stacked, row by row.
"""

from __future__ import annotations

import os
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Sequence

import torch

from toolkit.errors import ToolkitError

Row = dict[str, torch.Tensor]

DEFAULT_CACHE_BYTES = 512 << 20
"""Bytes of decoded rows a :class:`RowSource` keeps by default: the demo's whole training split (576 rows at
128², 0.33 MB each as the Gaussian stage reads them) fits; at the paper's 512² (5.2 MB a row) ~100 rows do."""


def default_workers() -> int:
    """Reading threads for this machine: half its cores, 1 to 4 (the rest train)."""
    return max(1, min(4, (os.cpu_count() or 2) // 2))


def row_nbytes(row: Row) -> int:
    return sum(t.untyped_storage().nbytes() for t in row.values())


class RowSource:
    """Rows ``convert(dataset[i])`` of a dataset, read when asked for.

    Args:
        dataset: a map-style dataset (:class:`train.data.dataset.GazeDataset`) whose items are dicts.
        convert: item -> the row's tensors kept (the rest of the item is dropped at once).
        cache_bytes: decoded rows kept, counted in bytes of their tensors. The first rows read are kept until the
            budget is spent and are never evicted. Why not least-recently-used: the Gaussian stage draws rows
            uniformly, where both keep ~budget/N of the draws, but the estimator goes through its rows epoch by
            epoch, where an LRU cache smaller than the split evicts every row just before it comes round again.
        workers: threads that read a batch's rows at once and read :meth:`prefetch`-ed rows while the caller
            computes (h5py serializes its own calls; decoding, resizing and compositing run in parallel). 0:
            every row is read in the calling thread when it is asked for.
    """

    def __init__(self, dataset, convert: Callable[[dict], Row], *, cache_bytes: int = DEFAULT_CACHE_BYTES,
                 workers: int = 0):
        if cache_bytes < 0 or workers < 0:
            raise ToolkitError(f"RowSource: expected cache_bytes >= 0 and workers >= 0, got {cache_bytes}, {workers}")
        self.dataset, self.convert = dataset, convert
        self.cache_bytes, self.workers = int(cache_bytes), int(workers)
        self._cache: dict[int, Row] = {}
        self._cached_bytes = 0
        self._pending: dict[int, Future] = {}
        self._pool: ThreadPoolExecutor | None = None
        self.reads = self.hits = 0

    def __len__(self) -> int:
        return len(self.dataset)

    @property
    def cached_bytes(self) -> int:
        return self._cached_bytes

    def _read(self, i: int) -> Row:
        return self.convert(self.dataset[i])

    def _submit(self, i: int) -> Future:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="rows")
        return self._pool.submit(self._read, i)

    def _check(self, indices: Sequence[int]) -> list[int]:
        out = [int(i) for i in indices]
        bad = [i for i in out if not 0 <= i < len(self)]
        if bad:
            raise ToolkitError(f"RowSource: row {bad[0]} is outside the split's {len(self)} rows")
        return out

    def _keep(self, i: int, row: Row) -> None:
        size = row_nbytes(row)
        if self._cached_bytes + size <= self.cache_bytes:
            self._cache[i] = row
            self._cached_bytes += size

    def prefetch(self, indices: Sequence[int]) -> None:
        """Start reading ``indices`` in the worker threads (no-op without workers); they replace an earlier
        prefetch's rows not asked for since, so at most one batch waits."""
        if self.workers == 0:
            return
        wanted = [i for i in dict.fromkeys(self._check(indices)) if i not in self._cache]
        for i in set(self._pending) - set(wanted):
            self._pending.pop(i).cancel()
        for i in wanted:
            if i not in self._pending:
                self._pending[i] = self._submit(i)

    def rows(self, indices: Sequence[int]) -> list[Row]:
        """The rows ``indices`` (repeats allowed), in order; cached rows are shared, not copied."""
        indices = self._check(indices)
        got: dict[int, Row] = {}
        todo: dict[int, Future | None] = {}
        for i in dict.fromkeys(indices):
            if i in self._cache:
                got[i] = self._cache[i]
                self.hits += 1
            elif i in self._pending:
                todo[i] = self._pending.pop(i)
            else:
                todo[i] = self._submit(i) if self.workers > 1 else None
        for i, fut in todo.items():
            got[i] = self._read(i) if fut is None else fut.result()
            self.reads += 1
            self._keep(i, got[i])
        return [got[i] for i in indices]

    def stack(self, indices: Sequence[int]) -> Row:
        """{key: [B, ...]} the rows ``indices`` stacked, in order."""
        rows = self.rows(indices)
        if not rows:
            raise ToolkitError("RowSource.stack: no rows asked for")
        return {k: torch.stack([r[k] for r in rows]) for k in rows[0]}

    def close(self) -> None:
        """Stop the reading threads (pending reads are dropped) and empty the cache."""
        for fut in self._pending.values():
            fut.cancel()
        self._pending = {}
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._cache, self._cached_bytes = {}, 0


class RowImages:
    """A stand-in for an ``[N, C, H, W]`` image tensor that code only indexes (``train_gaze_estimator``): the
    key ``key`` of a :class:`RowSource`'s rows, read when indexed, then the rows of ``extra`` (in memory).

    Supports ``shape``, ``dtype``, ``dim()``, ``len()`` and indexing by an int, a slice, a list or a 1-D tensor of
    indices, which gives a tensor equal to the one the stacked images would give."""

    def __init__(self, source: RowSource, key: str, row_shape: Sequence[int], dtype: torch.dtype,
                 extra: torch.Tensor | None = None):
        self.source, self.key, self.row_shape, self.dtype = source, key, tuple(row_shape), dtype
        if extra is not None and (tuple(extra.shape[1:]) != self.row_shape or extra.dtype != dtype):
            raise ToolkitError(f"RowImages: extra rows {list(extra.shape)} {extra.dtype} do not match the split's "
                               f"{list(self.row_shape)} {dtype}")
        self.extra = extra

    @property
    def shape(self) -> torch.Size:
        n = len(self.source) + (0 if self.extra is None else self.extra.shape[0])
        return torch.Size((n, *self.row_shape))

    def dim(self) -> int:
        return len(self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def cat(self, extra: torch.Tensor) -> RowImages:
        """These rows then ``extra`` [M, C, H, W] (what ``torch.cat([images, extra])`` gives)."""
        more = extra if self.extra is None else torch.cat([self.extra, extra])
        return RowImages(self.source, self.key, self.row_shape, self.dtype, more)

    def _indices(self, idx) -> list[int]:
        n = len(self)
        if isinstance(idx, int):
            idx = [idx]
        elif isinstance(idx, slice):
            idx = range(*idx.indices(n))
        idx = [int(i) for i in (idx.reshape(-1).tolist() if isinstance(idx, torch.Tensor) else idx)]
        idx = [i + n if i < 0 else i for i in idx]
        if any(not 0 <= i < n for i in idx):
            raise IndexError(f"RowImages: an index is outside the {n} rows")
        return idx

    def prefetch(self, idx) -> None:
        """Start reading the split's rows among ``idx`` (a later batch's) in the source's threads."""
        self.source.prefetch([i for i in self._indices(idx) if i < len(self.source)])

    def __getitem__(self, idx) -> torch.Tensor:
        if not isinstance(idx, (slice, torch.Tensor, list, tuple, range)) and hasattr(idx, "__index__"):
            return self[[int(idx)]][0]  # an int: one image [C, H, W]
        idx = self._indices(idx)
        out = torch.empty((len(idx), *self.row_shape), dtype=self.dtype)
        split = len(self.source)
        mine = [(k, i) for k, i in enumerate(idx) if i < split]
        for (k, _), row in zip(mine, self.source.rows([i for _, i in mine])):
            out[k] = row[self.key]
        for k, i in enumerate(idx):
            if i >= split:
                out[k] = self.extra[i - split]
        return out
