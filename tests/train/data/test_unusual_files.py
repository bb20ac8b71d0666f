"""Valid subject folders as researchers hold them: files copied from a Mac carry AppleDouble ``._*.h5`` companions
(Finder metadata, not HDF5) that a folder's reader skips; stored in other lossless ways, a file reads the same."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from tests.train.data.peer_fixtures import native_truth, write_ditgaze, write_gazegaussian
from toolkit.errors import ToolkitError
from train.data.dataset import APPLEDOUBLE_MAGIC, GazeDataset, find_subject_files


def _folder_with_mac_companions(tmp_path):
    folder = tmp_path / "subjects"
    folder.mkdir()
    write_ditgaze(folder / "subject0000.h5", native_truth(n_frames=1, n_cams=2, seed=1))
    (folder / "._subject0000.h5").write_bytes(APPLEDOUBLE_MAGIC + b"\x00\x02\x00\x00" + b"\x00" * 74)
    (folder / ".DS_Store").write_bytes(b"\x00\x00\x00\x01Bud1" + b"\x00" * 64)
    (folder / "README.txt").write_text("ETH-XGaze subjects\n")
    return folder


def test_a_folder_skips_the_appledouble_files_macos_leaves(tmp_path):
    folder = _folder_with_mac_companions(tmp_path)
    assert [p.name for p in find_subject_files(folder)] == ["subject0000.h5"]
    assert len(GazeDataset([folder])) == 2


def test_inspect_reads_a_folder_copied_from_a_mac(tmp_path, capsys):
    from train.data.__main__ import main

    folder = _folder_with_mac_companions(tmp_path)
    main(["inspect", str(folder), "--sheet", str(tmp_path / "sheet.png")])
    assert "subject0000" in capsys.readouterr().out


def test_a_dot_underscore_file_that_is_not_appledouble_is_still_read(tmp_path):
    """Only AppleDouble content is skipped: any other ``._*.h5`` file is a subject file (or refused as one)."""
    folder = tmp_path / "subjects"
    folder.mkdir()
    (folder / "._subject0001.h5").write_bytes(b"not hdf5 at all")
    assert [p.name for p in find_subject_files(folder)] == ["._subject0001.h5"]
    with pytest.raises(ToolkitError, match=r"\._subject0001.h5: not a readable HDF5 file"):
        GazeDataset([folder])


@pytest.mark.parametrize("name", ["subject0001.H5", "subject0001.hdf5"])
def test_a_subject_file_the_folder_would_not_list_is_named(tmp_path, name):
    """A folder lists its ``*.h5``: a subject under another suffix would be left out of the dataset unseen."""
    folder = _folder_with_mac_companions(tmp_path)
    write_ditgaze(folder / name, native_truth(n_frames=1, n_cams=2, seed=2))
    with pytest.raises(ToolkitError, match=rf"subjects: {name}: subject files are listed by the suffix \.h5"):
        find_subject_files(folder)


@pytest.mark.parametrize("storage", [dict(chunks=True, compression="gzip", shuffle=True, fletcher32=True),
                                     dict(chunks=True, compression="lzf"), dict(dtype=">f8")])
def test_other_lossless_storage_reads_the_same(tmp_path, storage):
    truth = native_truth(n_frames=2, n_cams=3, seed=4)
    plain = tmp_path / "plain" / "xgaze_subject0003.h5"
    plain.parent.mkdir()
    write_gazegaussian(plain, truth)
    other = tmp_path / "other" / plain.name
    other.parent.mkdir()
    with h5py.File(plain) as a, h5py.File(other, "w") as b:
        for k in a:
            arr, kw = a[k][()], dict(storage)
            if "dtype" in kw and arr.dtype.kind != "f":
                kw.pop("dtype")
            b.create_dataset(k, data=arr.astype(kw.pop("dtype", arr.dtype)), **kw)
        b.create_dataset("notes", data=np.arange(3))  # a key no layout knows
    ref, got = GazeDataset([plain]), GazeDataset([other])
    for i in range(len(ref)):
        for k, v in ref[i].items():
            np.testing.assert_allclose(got[i][k].numpy(), v.numpy(), atol=1e-7, err_msg=k)
