"""Evaluation pairing: GazeNeRF pairs, pairing files, generator-rendered redirection targets."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.train.data.conftest import needs_gl
from toolkit.errors import ToolkitError
from train.data.pairing import (
    SyntheticRedirectionPairs,
    gazenerf_pairs,
    load_pairing,
    save_pairing,
    synthetic_pairs,
)


def test_gazenerf_pairs_are_a_fixed_permutation():
    p = gazenerf_pairs()
    assert p.shape == (100, 2)
    np.testing.assert_array_equal(p[:, 0], np.arange(100))
    np.testing.assert_array_equal(np.sort(p[:, 1]), np.arange(100, 200))
    np.testing.assert_array_equal(p, gazenerf_pairs())
    assert not np.array_equal(p, gazenerf_pairs(seed=1))
    q = synthetic_pairs(36)
    assert q.shape == (18, 2) and q[:, 1].min() == 18


def test_pairing_files(tmp_path):
    save_pairing(tmp_path / "p.json", {"subject0003": gazenerf_pairs(5)})
    got = load_pairing(tmp_path / "p.json")
    np.testing.assert_array_equal(got["subject0003"], gazenerf_pairs(5))
    save_pairing(tmp_path / "empty.json", {"a": gazenerf_pairs(2), "b": np.zeros((0, 2), np.int64)})
    assert load_pairing(tmp_path / "empty.json")["b"].shape == (0, 2)  # what save_pairing writes loads back
    (tmp_path / "p.txt").write_text("# subject input target\nsubject0001 0 101\nsubject0001 1 150\n")
    np.testing.assert_array_equal(load_pairing(tmp_path / "p.txt")["subject0001"], [[0, 101], [1, 150]])
    (tmp_path / "bad.txt").write_text("subject0001 0\n")
    with pytest.raises(ToolkitError, match="bad.txt: not a pairing file"):
        load_pairing(tmp_path / "bad.txt")
    for name, text in (("triples.json", '{"s": [[1, 2, 3], [4, 5, 6]]}'), ("floats.json", '{"s": [[1.9, 7.5]]}')):
        (tmp_path / name).write_text(text)  # not silently reshaped or truncated into other pairs
        with pytest.raises(ToolkitError, match=rf"{name}: not a pairing file \(subject 's': expected a list of"):
            load_pairing(tmp_path / name)
    (tmp_path / "neg.json").write_text('{"s": [[0, -1]]}')
    with pytest.raises(ToolkitError, match="negative"):
        load_pairing(tmp_path / "neg.json")
    with pytest.raises(ToolkitError, match="no such pairing file"):
        load_pairing(tmp_path / "missing.json")


@needs_gl
def test_synthetic_targets_come_from_the_generator(subject_file):
    ev = SyntheticRedirectionPairs(subject_file, pairs=np.array([[4, 4], [4, 31], [10, 22]]))
    same = ev[0]
    # Target with the input's own gaze re-renders the stored input image exactly.
    torch.testing.assert_close(same["target"]["image"], same["input"]["image"], atol=1e-6, rtol=0)
    torch.testing.assert_close(same["target"]["head_mask"], same["input"]["head_mask"])
    other = ev[1]
    torch.testing.assert_close(other["target"]["pitchyaw_head"], ev.data[31]["pitchyaw_head"])
    # Only the eyes change: pixels away from both eye masks (input and target) are identical.
    eyes = sum(d[m][0] for d in (other["input"], other["target"]) for m in ("left_eye_mask", "right_eye_mask")) > 0
    eyes = torch.nn.functional.max_pool2d(eyes[None, None].float(), 7, 1, 3)[0, 0] > 0
    diff = (other["target"]["image"] - other["input"]["image"]).abs().amax(0)
    assert float(diff[~eyes].max()) < 1e-6 and float(diff[eyes].max()) > 0.1
    with pytest.raises(ToolkitError, match="pair rows must be in"):
        SyntheticRedirectionPairs(subject_file, pairs=np.array([[0, 36]]))
    assert len(SyntheticRedirectionPairs(subject_file)) == 18
