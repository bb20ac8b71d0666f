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


# GazeNeRF's configs/config_files/xgaze_evaluation_target_single_subject.txt (AlessandroRuzzi/GazeNeRF at
# eb0a5f1; ucwxb/GazeGaussian ships the same 400 bytes): 100 lines, a permutation of 100..199. GazeNeRF
# np.loadtxt's it (datasets/eth_xgaze.py:280) and gives input index i the target row target_idx[i]
# (eth_xgaze.py:358-359), in one unshuffled loader of inputs 0..99 per subject (utils/metrics_utils.py:110-112).
GAZENERF_XGAZE_TARGETS = (
    "111 102 161 142 123 138 196 141 136 165 190 187 151 178 148 172 158 114 189 109 157 194 179 163 129 181 173 "
    "130 147 153 144 168 152 169 160 117 155 134 121 198 174 150 166 145 167 132 103 188 108 146 128 120 184 131 "
    "137 149 139 183 100 113 112 197 159 182 107 177 133 115 191 175 176 171 143 118 125 156 195 192 193 106 180 "
    "135 140 110 170 126 124 104 185 119 162 164 154 122 101 116 199 105 186 127").split()


def test_gazenerfs_target_list_pairs_input_i_with_row_list_i_for_every_subject(tmp_path):
    from train.data.pairing import ANY_SUBJECT, subject_pairing

    assert sorted(map(int, GAZENERF_XGAZE_TARGETS)) == list(range(100, 200))
    path = tmp_path / "xgaze_evaluation_target_single_subject.txt"
    path.write_text("".join(t + "\n" for t in GAZENERF_XGAZE_TARGETS))  # the file's exact bytes
    assert path.stat().st_size == 400
    got = load_pairing(path)
    assert list(got) == [ANY_SUBJECT]
    want = np.stack([np.arange(100), np.array(GAZENERF_XGAZE_TARGETS, np.int64)], 1)
    np.testing.assert_array_equal(got[ANY_SUBJECT], want)
    assert got[ANY_SUBJECT][0].tolist() == [0, 111] and got[ANY_SUBJECT][99].tolist() == [99, 127]
    # The same list for every held-out subject; a subject a JSON file names keeps its own pairs.
    assert subject_pairing(got, "subject0003") is got[ANY_SUBJECT] and subject_pairing(None, "s") is None
    both = {"subject0003": np.array([[0, 1]]), ANY_SUBJECT: want}
    assert subject_pairing(both, "subject0003").tolist() == [[0, 1]] and subject_pairing(both, "x") is want
    save_pairing(tmp_path / "saved.json", got)  # "*" survives a JSON round trip
    np.testing.assert_array_equal(load_pairing(tmp_path / "saved.json")[ANY_SUBJECT], want)
    # Whitespace separated on one line, with a comment: the same list.
    (tmp_path / "one_line.txt").write_text("# targets\n" + " ".join(GAZENERF_XGAZE_TARGETS) + "\n")
    np.testing.assert_array_equal(load_pairing(tmp_path / "one_line.txt")[ANY_SUBJECT], want)


def test_integer_only_pairing_text_is_a_target_list_or_refused(tmp_path):
    (tmp_path / "small.txt").write_text("5\n3\n4\n")  # a scaled-down list: rows 0..2 -> a permutation of 3..5
    assert load_pairing(tmp_path / "small.txt")["*"].tolist() == [[0, 5], [1, 3], [2, 4]]
    # Several integers on several lines: a target list or numbered subjects' lines? Refused, never guessed.
    (tmp_path / "grid.txt").write_text("3 0 101\n3 1 150\n")
    with pytest.raises(ToolkitError, match=r"grid.txt: not a pairing file \(integers only, several on a line"):
        load_pairing(tmp_path / "grid.txt")
    (tmp_path / "neg.txt").write_text("5\n-3\n")
    with pytest.raises(ToolkitError, match="neg.txt: subject '\\*' has negative row indices"):
        load_pairing(tmp_path / "neg.txt")
    (tmp_path / "huge.txt").write_text("5\n" + "9" * 30 + "\n")
    with pytest.raises(ToolkitError, match="huge.txt: not a pairing file"):
        load_pairing(tmp_path / "huge.txt")
    (tmp_path / "mixed.txt").write_text("subject0001 0 101\n7\n")  # a subject's line: the line form, one bad line
    with pytest.raises(ToolkitError, match="line 2: expected 'subject input_row target_row'"):
        load_pairing(tmp_path / "mixed.txt")


def _real_like(path, n: int, seed: int = 0):
    """A numpy-built subject file without ``subject_params``: what a real (captured) subject file looks like."""
    from tests.train.data.tiny_subject import tiny_attrs, tiny_rows, tiny_subject_arrays
    from train.data.format import write_subject_h5

    attrs = {k: v for k, v in tiny_attrs().items() if k != "subject_params"}
    return write_subject_h5(path, tiny_rows(n, seed=seed), subject=tiny_subject_arrays(), attrs=attrs)


def test_real_files_get_their_stored_target_rows(tmp_path):
    from tests.train.data.tiny_subject import write_tiny_subject
    from train.data.dataset import GazeDataset
    from train.data.pairing import StoredRedirectionPairs, is_synthetic_file, redirection_pairs

    real = _real_like(tmp_path / "subject0007.h5", 6)
    assert not is_synthetic_file(real) and is_synthetic_file(write_tiny_subject(tmp_path / "synth" / "s.h5"))
    pairs = redirection_pairs(real, np.array([[0, 4], [2, 3]]), res=32)
    assert isinstance(pairs, StoredRedirectionPairs) and pairs.protocol == "stored" and len(pairs) == 2
    data = GazeDataset([real], res=32)
    item = pairs[1]
    assert item["pair"].tolist() == [2, 3]
    for who, row in (("input", 2), ("target", 3)):  # the rows as the dataset gives them: image on white, camera
        for key in ("image", "head_mask", "viewmat", "K", "pose", "pitchyaw_head", "landmarks"):
            torch.testing.assert_close(item[who][key], data[row][key], rtol=0, atol=0)
    default = redirection_pairs(real, res=32).pairs  # no pairing: the first half -> a permutation of the second
    assert default.tolist() == synthetic_pairs(6).tolist() and sorted(default[:, 1]) == [3, 4, 5]
    with pytest.raises(ToolkitError, match="pair rows must be in"):
        StoredRedirectionPairs(real, np.array([[0, 6]]))


def test_pairing_rows_are_checked_against_every_subject_before_any_work(tmp_path):
    from train.data.pairing import check_pairing_rows

    six, one = _real_like(tmp_path / "subject0001.h5", 6), _real_like(tmp_path / "subject0002.h5", 1)
    check_pairing_rows([six], None)
    check_pairing_rows([six], {"*": np.array([[0, 5], [1, 3]])})
    with pytest.raises(ToolkitError) as err:  # the file, the pair, its rows and the file's row count
        check_pairing_rows([six], {"*": np.array([[0, 5], [1, 3], [2, 6], [3, 9]])}, "the pairing file p.txt")
    assert str(err.value) == (f"{six}: pair 2 of the pairing file p.txt (input row 2, target row 6) is out of range: "
                              f"the file has 6 rows (0-5); 2 of its 4 pairs are")
    with pytest.raises(ToolkitError, match=r"subject0002.h5: 1 row; the generated pairing .* needs at least 2 rows: "
                                           r"give eval.pairing_file"):
        check_pairing_rows([six, one], None)
    check_pairing_rows([one], {"subject0002": np.array([[0, 0]])})  # a pairing may pair a 1-row file
    with pytest.raises(ToolkitError, match=r"no pairs for test subject\(s\) \['subject0002'\]"):
        check_pairing_rows([six, one], {"subject0001": np.array([[0, 1]])})
