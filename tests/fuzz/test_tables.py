"""Property tests of the small text readers: pairing files (text and JSON) and labels CSVs. Any text either
parses into what the reader promises or is one ToolkitError line naming the file; never another exception."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from apps.labels_table import read_labels
from toolkit.errors import ToolkitError
from train.data.pairing import load_pairing

TOKENS = st.sampled_from(["subject0001", "s", "0", "1", "99", "-1", "1e3", "1.5", "9" * 40, "#", ",", " ", "\t",
                          "\n", "[", "]", "{", "}", '"', ":", "null", "true", "\x00", "é", "[[0, 1]]"])


def _one_line_about(err: ToolkitError, path) -> None:
    text = str(err)
    assert "\n" not in text and str(path) in text, text


@given(st.lists(TOKENS, max_size=40).map("".join), st.sampled_from([".txt", ".json"]))
def test_any_pairing_text_parses_or_is_one_line(tmp_path_factory, text, suffix):
    path = tmp_path_factory.mktemp("pairs") / f"pairs{suffix}"
    path.write_text(text, encoding="utf-8")
    try:
        pairs = load_pairing(path)
    except ToolkitError as e:
        _one_line_about(e, path)
        return
    assert pairs and all(v.dtype == np.int64 and v.ndim == 2 and v.shape[1] == 2 and (v >= 0).all()
                         for v in pairs.values())


@given(st.binary(max_size=200), st.sampled_from([".txt", ".json"]))
def test_any_pairing_bytes_parse_or_are_one_line(tmp_path_factory, data, suffix):
    path = tmp_path_factory.mktemp("pairs") / f"pairs{suffix}"
    path.write_bytes(data)
    try:
        load_pairing(path)
    except ToolkitError as e:
        _one_line_about(e, path)


@pytest.mark.parametrize("text", ["[" * 100_000 + "]" * 100_000, '{"s": [[0, ' + "9" * 5000 + ']]}',
                                  '{"s": [[0, 18446744073709551616]]}', '{"s": [[0, 1], [2]]}'])
def test_hostile_pairing_json_is_one_line(tmp_path, text):
    path = tmp_path / "pairs.json"
    path.write_text(text)
    with pytest.raises(ToolkitError) as err:
        load_pairing(path)
    _one_line_about(err.value, path)


CELLS = st.sampled_from(["", "0", "10", "-95", "200", "1e300", "nan", "inf", "x", "img0.png", "missing.png",
                         "code0.npy", "mask0.png", "img0.png,1", '"', "\x00", "  7 "])
HEADERS = st.sampled_from(["image,head_pitch,head_yaw,gaze_pitch,gaze_yaw",
                           "image,head_pitch,head_yaw,gaze_pitch,gaze_yaw,code,mask,focal,distance",
                           "image,head_pitch", "image,image,head_pitch,head_yaw", ""])


@pytest.fixture(scope="module")
def crop_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("crops")
    cv2.imwrite(str(folder / "img0.png"), np.full((16, 16, 3), 128, np.uint8))
    cv2.imwrite(str(folder / "mask0.png"), np.full((16, 16), 255, np.uint8))
    np.save(folder / "code0.npy", np.zeros(144, np.float32))
    return folder


@given(HEADERS, st.lists(st.lists(CELLS, max_size=10).map(",".join), max_size=4))
def test_any_labels_csv_parses_or_is_one_line(crop_folder, header, rows):
    path = crop_folder / "labels.csv"
    path.write_text("\n".join([header, *rows]) + "\n", encoding="utf-8")
    try:
        parsed, size = read_labels(path)
    except ToolkitError as e:
        assert "\n" not in str(e)
        return
    assert size == 16 and all(np.isfinite(r.focal) and r.focal > 0 for r in parsed)
