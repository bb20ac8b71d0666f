"""The training split read a batch at a time (``open_split``, ``RowSource``, ``RowImages``): the same tensors as
the whole split in memory (``load_split``), and only a bounded cache of rows held."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from train.data.format import write_subject_h5
from train.training.trainer import ROW_KEYS, TrainRows, load_split, open_split

ROWS, STORED = 6, 24


def _subject(path, seed: int, *, with_cam_gaze: bool = True):
    """A subject file of ROWS rows at STORED² with random images and masks (soft edges after a resize)."""
    from tests.train.data.tiny_subject import tiny_attrs, tiny_rows, tiny_subject_arrays

    rng = np.random.default_rng(seed)
    rows = tiny_rows(ROWS, STORED, seed=seed)
    for key in ("head_mask", "left_eye_mask", "right_eye_mask"):
        rows[key] = (rng.random((ROWS, STORED, STORED)) < 0.5).astype(np.uint8) * 255
    rows["pose"] = rng.normal(0, 0.1, (ROWS, 6)).astype(np.float32)
    if not with_cam_gaze:  # the dataset derives it from the head-frame gaze
        del rows["pitchyaw_cam"]
    return write_subject_h5(path, rows, subject=tiny_subject_arrays(), attrs=tiny_attrs())


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    d = tmp_path_factory.mktemp("split")
    return [_subject(d / "subject0000.h5", 1), _subject(d / "subject0001.h5", 2, with_cam_gaze=False)]


def _equal(a: dict, b: dict) -> None:
    assert list(a) == list(b)
    for k in a:
        assert a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]), k


@pytest.mark.parametrize("res", [16, STORED, 32])
@pytest.mark.parametrize("cache_bytes, workers", [(0, 0), (1 << 30, 0), (0, 2), (1 << 30, 3)])
def test_rows_read_a_batch_at_a_time_equal_the_split_in_memory(split, res, cache_bytes, workers):
    whole = load_split(split, "all", res)
    rows = open_split(split, "all", res, cache_bytes=cache_bytes, workers=workers)
    try:
        assert len(rows) == len(whole) == 2 * ROWS and rows.res == whole.res == res
        g = torch.Generator().manual_seed(0)
        for _ in range(3):  # repeats within and across batches: cached rows, prefetched rows, fresh reads
            idx = torch.randint(0, len(whole), (5,), generator=g)
            rows.prefetch(torch.randint(0, len(whole), (4,), generator=g))
            _equal(rows.take(idx, "cpu"), whole.take(idx, "cpu"))
        every = torch.arange(len(whole))
        _equal(rows.take(every, "cpu"), whole.take(every, "cpu"))
        b = rows.take(every[:3], "cpu")
        assert torch.equal(rows.head_to_camera(b), whole.head_to_camera(b))
    finally:
        rows.close()


def test_init_rgb_reads_the_rows_the_split_in_memory_gives_it(split, monkeypatch):
    """``init_rgb`` takes its evenly spaced rows itself: rgb_init receives the tensors it picked from the whole
    split before."""
    import train.model.rgb_init as rgb_init
    from train.training.trainer import init_rgb

    seen = []
    monkeypatch.setattr(rgb_init, "init_rgb_from_images", lambda model, *args, **kw: seen.append(args) or 1.0)
    model = SimpleNamespace(face_features=torch.zeros(1))
    whole = load_split(split, "all", 16)
    init_rgb(model, open_split(split, "all", 16, workers=0))
    n = len(whole)
    idx = torch.linspace(0, n - 1, min(n, 64)).round().long().unique()  # rgb_init's choice on the whole split
    want = [getattr(whole, k)[idx] for k in ("image", "head", "code", "pose", "gaze_head", "viewmat", "K")]
    assert len(seen) == 1 and all(torch.equal(a, b) for a, b in zip(seen[0], want))


def _held_tensors(obj, depth: int = 0) -> list[torch.Tensor]:
    """The tensors reachable from ``obj``'s attributes, dicts, lists and tuples (a few levels deep)."""
    if isinstance(obj, torch.Tensor):
        return [obj]
    if depth > 5 or isinstance(obj, (str, bytes, int, float, type(None))):
        return []
    if isinstance(obj, dict):
        items = list(obj.values())
    elif isinstance(obj, (list, tuple)):
        items = list(obj)
    elif hasattr(obj, "__dict__"):
        items = list(vars(obj).values())
    else:
        return []
    return [t for it in items for t in _held_tensors(it, depth + 1)]


def test_the_training_data_holds_no_image_of_the_whole_split(split):
    """What the Gaussian stage trains on holds at most its cache's rows however many rows it reads: no tensor
    of the split's N rows, and every row read with the cache off leaves nothing behind."""
    from train.data.dataset import GazeDataset
    from train.data.rows import row_nbytes
    from train.training.trainer import train_row

    one_row = row_nbytes(train_row(GazeDataset(split, res=16)[0]))  # image, head and eye masks, the labels
    assert one_row < 5 * 16 * 16 * 4 + 2048
    rows = open_split(split, "all", 16, cache_bytes=3 * one_row, workers=2)
    try:
        for i in range(len(rows)):
            rows.take(torch.tensor([i, i]), "cpu")
        assert rows.source.reads == len(rows)
        assert len(rows.source._cache) == 3 and rows.source.cached_bytes <= 3 * one_row
        held = _held_tensors(rows)
        assert held and all(t.shape[0] != len(rows) for t in held if t.dim())
        assert sum(t.untyped_storage().nbytes() for t in held) <= 3 * one_row
    finally:
        rows.close()
    off = open_split(split, "all", 16, cache_bytes=0, workers=0)
    for i in range(len(off)):
        off.take(torch.tensor([i]), "cpu")
    assert off.source.cached_bytes == 0 and not _held_tensors(off)


def test_a_prefetched_batch_is_read_once_and_a_stale_one_dropped(split):
    rows = open_split(split, "all", 16, cache_bytes=0, workers=2)
    try:
        rows.prefetch(torch.tensor([0, 1, 1]))
        rows.prefetch(torch.tensor([2, 3]))  # replaces the first: at most one batch waits
        assert sorted(rows.source._pending) == [2, 3]
        rows.take(torch.tensor([3, 2, 4]), "cpu")
        assert rows.source.reads == 3 and not rows.source._pending
    finally:
        rows.close()


def test_the_trainer_reads_ahead_the_rows_its_next_step_draws():
    """``GaussianTrainer._prefetch`` guesses a step's rows as the loop will draw them: the first draw of the
    step's generator, this rank's shard of them."""
    from train.training.loop import step_generator
    from train.training.trainer import GaussianTrainer, drawn_rows

    asked = []
    data = type("D", (), {"prefetch": lambda self, idx: asked.append(idx), "__len__": lambda self: 50})()
    trainer = SimpleNamespace(data=data, cfg=SimpleNamespace(batch=4), seed=3, _rows=lambda x: x[1:3])
    GaussianTrainer._prefetch(trainer, 7)
    want = torch.randint(0, 50, (4,), generator=step_generator(3, 7))  # the first draw of GaussianTrainer.step
    assert torch.equal(drawn_rows(50, 4, 3, 7), want)
    assert len(asked) == 1 and torch.equal(asked[0], want[1:3])
    GaussianTrainer._prefetch(SimpleNamespace(data=SimpleNamespace()), 7)  # in-memory data: nothing to read ahead


def test_row_images_index_like_the_stacked_tensor(split):
    from train.data.dataset import GazeDataset
    from train.data.rows import RowImages, RowSource

    ds = GazeDataset(split, res=16)
    src = RowSource(ds, lambda it: {"image": (it["image"] * 255).round().to(torch.uint8)}, cache_bytes=0, workers=2)
    stacked = torch.stack([src.rows([i])[0]["image"] for i in range(len(ds))])
    extra = torch.randint(0, 256, (3, 3, 16, 16), dtype=torch.uint8)
    images = RowImages(src, "image", (3, 16, 16), torch.uint8).cat(extra)
    full = torch.cat([stacked, extra])
    try:
        assert images.shape == full.shape and images.dim() == 4 and len(images) == len(full)
        images.prefetch(torch.tensor([1, 2, len(full) - 1]))  # the extra rows are in memory: not read
        assert sorted(src._pending) == [1, 2]
        for idx in (torch.tensor([0, 13, 5, 14, 5]), slice(2, 9), slice(None, None, 4), [-1, 0], 12, -2, np.int64(3)):
            assert torch.equal(images[idx], full[idx])
        with pytest.raises(IndexError):
            images[torch.tensor([len(full)])]
    finally:
        src.close()


def test_row_keys_are_the_fields_of_the_split_in_memory():
    from train.training.trainer import TrainBatchData

    assert list(ROW_KEYS) == list(TrainBatchData.__dataclass_fields__)
    assert TrainRows.head_to_camera is TrainBatchData.head_to_camera
