"""The codec stage reads its split a batch at a time: the same images and pixel weights as the whole split in
memory, for whatever rows a batch draws."""

from __future__ import annotations

import torch

from train.model.codec import eye_weights
from train.stages.codec import codec_rows
from train.training.trainer import load_split


def test_streamed_codec_rows_equal_the_split_in_memory(tiny_run):
    files = sorted((tiny_run / "data").glob("*.h5"))[:1]
    whole = load_split(files, "all", 32)
    images, weights = codec_rows(files, 32, "auto", 100.0)
    try:
        idx = torch.tensor([3, 0, 3, len(images) - 1])
        assert images.shape == whole.image.shape and torch.equal(images[idx], whole.image[idx])
        assert torch.equal(weights[idx], eye_weights(whole.eyes * whole.head, 100.0)[idx])
        assert torch.equal(images[:5], whole.image[:5])
    finally:
        images.source.close()
    none, no_weights = codec_rows(files, 32, "auto", 0.0)
    none.source.close()
    assert no_weights is None
