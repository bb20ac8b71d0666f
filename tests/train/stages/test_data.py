"""Stage data: the held-out subjects get their own frame count."""

import h5py

from train import run

TINY = ["--preset", "tiny"]


def test_data_stage_gives_the_held_out_subjects_their_frames(tmp_path):
    d = tmp_path / "run"
    assert run.main([*TINY, "--run-dir", str(d), "--stages", "data", "data.test_frames=4"]) == 0
    from train.data.dataset import find_subject_files, split_files

    rows = {}
    for split in ("train", "test"):
        for p in split_files(find_subject_files([d / "data"]), split):
            with h5py.File(p) as f:
                rows[split] = len(f["pitchyaw_head"])
    assert rows == {"train": 18, "test": 72}  # 1 frame per training subject (tiny), 4 held out, 18 cameras
