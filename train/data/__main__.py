"""CLI: ``python -m train.data synth ...`` writes synthetic subjects; ``inspect PATH`` summarizes files;
``export`` writes them in a peer's layout.

    python -m train.data synth --subjects 8 --frames 10 --res 128 --out data/synth
    python -m train.data inspect data/synth            # table + data/synth/contact_sheet.png
    python -m train.data inspect data/synth/subject0000.h5 --sheet out/sheet.png --n 18
    python -m train.data export data/synth out/gg     # xgaze_subjectNNNN.h5 + train_test_split.json
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from toolkit.errors import CliParser, ToolkitError, run_cli
from toolkit.io import check_not_an_input, check_output_folder
from toolkit.limits import check_allocation, check_count


def _table(rows: list[dict], columns: list[str]) -> str:
    cells = [[str(r.get(c, "")) for c in columns] for r in rows]
    widths = [max(len(c), *(len(x[i]) for x in cells)) for i, c in enumerate(columns)]
    line = lambda vals: "| " + " | ".join(v.rjust(w) for v, w in zip(vals, widths, strict=True)) + " |"  # noqa: E731
    return "\n".join([line(columns), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + [line(x) for x in cells])


def summarize(path: Path, info: dict, layout: str = "ditgaze") -> dict:
    """One row of the inspect table; the gaze in native conventions whatever the file's ``layout``."""
    from toolkit.h5 import h5_dataset, has_key, open_h5, read_array, read_selection
    from train.data.layout_conversion import to_native

    with open_h5(path) as f:  # validated by GazeDataset: the labels fit memory, one mask row does
        g = np.degrees(to_native(layout, {"pitchyaw_head": read_array(path, f, "pitchyaw_head")})["pitchyaw_head"])
        hp = np.degrees(read_array(path, f, "face_head_pose"))
        cams = len(np.unique(read_array(path, f, "cam_index")))
        frames = len(np.unique(read_array(path, f, "frame_index"))) if has_key(path, f, "frame_index") else "-"
        mask = h5_dataset(path, f, "head_mask")
        rows = np.linspace(0, info["n"] - 1, 8).astype(int)
        cov = float(np.mean([read_selection(path, "head_mask", mask, int(i)).mean() / 255 for i in rows]))
    return {
        "file": path.name, "layout": layout, "images": info["n"], "res": f"{info['width']}x{info['height']}", "cameras": cams,
        "frames": frames, "vertices": "-" if info["n_vertices"] is None else info["n_vertices"],
        "gaze pitch (deg)": f"{g[:, 0].min():.0f}..{g[:, 0].max():.0f}",
        "gaze yaw (deg)": f"{g[:, 1].min():.0f}..{g[:, 1].max():.0f}",
        "head pitch/yaw (deg)": f"{hp[:, 0].min():.0f}..{hp[:, 0].max():.0f} / {hp[:, 1].min():.0f}..{hp[:, 1].max():.0f}",
        "head mask": f"{cov:.0%}",
        "extra keys": ",".join(info["optional"] + info["subject_keys"]) or "-",
    }


def draw_tile(sample: dict, size: int) -> np.ndarray:
    """One annotated tile (RGB uint8): eye masks tinted, head-mask outline, landmarks, gaze arrow."""
    import cv2

    img = (sample["image"].numpy().transpose(1, 2, 0) * 255).astype(np.uint8).copy()
    H = img.shape[0]
    for m, col in (("left_eye_mask", (255, 60, 60)), ("right_eye_mask", (60, 60, 255))):
        a = (sample[m][0].numpy() > 0.5)[..., None]
        img = np.where(a, (0.55 * img + 0.45 * np.array(col)).astype(np.uint8), img)
    img = cv2.resize(img, (size, size), interpolation=cv2.INTER_NEAREST if size > H else cv2.INTER_AREA)
    head = cv2.resize((sample["head_mask"][0].numpy() > 0.5).astype(np.uint8), (size, size),
                      interpolation=cv2.INTER_NEAREST)
    contours, _ = cv2.findContours(head, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(img, contours, -1, (0, 200, 0), 1)
    s = size / H
    lm = sample["landmarks"].numpy() * s
    for k, (x, y) in enumerate(lm):
        col = (255, 200, 0) if 36 <= k <= 47 else (0, 200, 255)
        cv2.circle(img, (int(round(x - 0.5)), int(round(y - 0.5))), max(1, size // 160), col, -1)
    if "pitchyaw_cam" in sample:
        for eye in (lm[36:42].mean(0), lm[42:48].mean(0)):
            gaze_arrow(img, eye, sample["pitchyaw_cam"], size * 0.12)
    return img


def gaze_arrow(img: np.ndarray, start: np.ndarray, pitchyaw, length: float) -> None:
    """Draw the camera-frame gaze (pitch, yaw radians, native conventions) as an arrow from ``start`` (x, y)."""
    import cv2

    p, yw = (float(v) for v in pitchyaw)
    end = start + np.array([-math.cos(p) * math.sin(yw), -math.sin(p)]) * length
    cv2.arrowedLine(img, tuple(int(v) for v in start), tuple(int(v) for v in end), (255, 255, 0), 1, tipLength=0.25)


def contact_sheet(dataset, indices: Sequence[int], out: Path, *, tile: int = 160, cols: int = 6) -> Path:
    """A sheet of :func:`draw_tile` tiles of ``dataset``'s rows ``indices``, written (atomically) to ``out``."""
    _check_sheet(len(indices), tile, cols)
    return write_sheet([draw_tile(dataset[int(i)], tile) for i in indices], out, tile=tile, cols=cols)


def _check_sheet(n: int, tile: int, cols: int) -> None:
    # the tiles, the sheet and its PNG encoding: three images of the sheet's size at most
    check_allocation(3 * math.ceil(n / cols) * cols * tile * tile * 3, f"the contact sheet ({n} images of {tile} "
                     "pixels)", hint="lower --n or --tile")


def write_sheet(tiles: list[np.ndarray], out: Path, *, tile: int, cols: int = 6) -> Path:
    """[tile, tile, 3] uint8 RGB images, ``cols`` a row on white, as a PNG at ``out`` (atomically)."""
    import cv2

    from toolkit.io import atomic_write_bytes

    rows = math.ceil(len(tiles) / cols)
    sheet = np.full((rows * tile, cols * tile, 3), 255, np.uint8)
    for k, t in enumerate(tiles):
        r, c = divmod(k, cols)
        sheet[r * tile:(r + 1) * tile, c * tile:(c + 1) * tile] = t
    ok, buf = cv2.imencode(".png", sheet[..., ::-1])
    if not ok:
        raise ToolkitError(f"{out}: could not encode the contact sheet")
    atomic_write_bytes(out, buf.tobytes())
    return out


def cmd_synth(a) -> int:
    import h5py

    from train.data.dataset import check_no_other_dataset
    from train.data.generate import synth_dataset

    check_no_other_dataset(a.out, [*(f"subject{s:04d}.h5" for s in range(a.subjects)), "split.json"], "--out",
                           "synth")
    t0 = time.perf_counter()
    paths = synth_dataset(a.out, n_subjects=a.subjects, n_frames=a.frames, res=a.res, seed=a.seed,
                          light_jitter=a.light_jitter, test_frames=a.test_frames, scale=a.scale)
    dt = time.perf_counter() - t0
    n = 0
    for p in paths:
        with h5py.File(p, "r") as f:
            n += len(f["pitchyaw_head"])
    print(f"wrote {len(paths)} subjects ({n} images at {a.res}x{a.res}) to {a.out} in {dt:.1f} s "
          f"({n / dt:.1f} images/s)")
    return 0


def _layout_line(name: str) -> str:
    from train.data.layouts import get_layout

    lay = get_layout(name)
    return (f"layout {name}: {lay.description}; gaze {lay.gaze_sign} ({lay.gaze_frame} frame, read as native "
            f"pitch = asin(-g_y)); 3D keys: {lay.frame_3d or 'none'}; codes: "
            f"{' + '.join(f'{n} {w}' for n, w in lay.codes) or 'none'}")


def _sheet_writable(a, sheet: Path) -> bool:
    """Whether the sheet goes to ``sheet``: a default one beside a read-only dataset is skipped, and said so."""
    if not a.sheet and not os.access(sheet.parent, os.W_OK | os.X_OK):  # a shared, read-only dataset: the table
        print(f"contact sheet: not written, {sheet.parent} is read-only here (give --sheet PATH to write one)")
        return False
    return True


def cmd_inspect(a) -> int:
    from train.data.dataset import GazeDataset, find_subject_files
    from train.data.patches import release_layout

    p = Path(a.path)
    sheet = Path(a.sheet) if a.sheet else (p / "contact_sheet.png" if p.is_dir() else p.with_name(p.stem + "_sheet.png"))
    if sheet.suffix.lower() != ".png":
        raise ToolkitError(f"--sheet {sheet}: the contact sheet is a PNG; expected a file name ending in .png")
    if a.sheet:
        check_output_folder(sheet.parent, "--sheet")
    files = find_subject_files([a.path])
    if release_layout(files, a.layout):
        return inspect_release(a, files, sheet)
    ds = GazeDataset(a.path, res=None, layout=a.layout)
    print(_table([summarize(Path(i["path"]), i, lay) for i, lay in zip(ds.info, ds.layouts)],
                 ["file", "layout", "images", "res", "cameras", "frames", "vertices", "gaze pitch (deg)",
                  "gaze yaw (deg)", "head pitch/yaw (deg)", "head mask", "extra keys"]))
    for name in sorted(set(ds.layouts)):
        print(_layout_line(name))
    check_not_an_input(sheet, [p, *(Path(i["path"]) for i in ds.info)], "--sheet")
    if _sheet_writable(a, sheet):
        n = min(a.n, len(ds))
        idx = np.linspace(0, len(ds) - 1, n).round().astype(int) if n > 0 else []
        contact_sheet(ds, idx, sheet, tile=a.tile)
        print(f"contact sheet: {sheet} ({n} images: eye masks tinted red/blue, head mask outlined green, "
              "eye landmarks yellow, others cyan, camera-frame gaze arrows)")
    ds.close()
    return 0


def inspect_release(a, files: list[Path], sheet: Path) -> int:
    """``inspect`` of ETH-XGaze release files (``train.data.patches``): their table (gaze and head pose in native
    conventions; a held-out test subject has no gaze) and a sheet of face patches with their gaze arrows."""
    import cv2

    from train.data.patches import read_patches, release_summary

    summaries = [release_summary(f) for f in files]  # every file checked before anything is printed or drawn
    deg = lambda x, i: f"{np.degrees(x[:, i]).min():.0f}..{np.degrees(x[:, i]).max():.0f}"  # noqa: E731
    print(_table([{"file": f.name, "layout": "xgaze", "images": s["n"], "res": f"{s['size']}x{s['size']}",
                   "cameras": s["cameras"], "frames": s["frames"],
                   "gaze pitch (deg)": "-" if s["gaze"] is None else deg(s["gaze"], 0),
                   "gaze yaw (deg)": "-" if s["gaze"] is None else deg(s["gaze"], 1),
                   "head pitch/yaw (deg)": f"{deg(s['head_pose'], 0)} / {deg(s['head_pose'], 1)}",
                   "landmarks": "yes" if s["landmarks"] else "-"} for f, s in zip(files, summaries)],
                 ["file", "layout", "images", "res", "cameras", "frames", "gaze pitch (deg)", "gaze yaw (deg)",
                  "head pitch/yaw (deg)", "landmarks"]))
    print(_layout_line("xgaze"))
    check_not_an_input(sheet, [Path(a.path), *files], "--sheet")
    if not _sheet_writable(a, sheet):
        return 0
    starts = np.concatenate([[0], np.cumsum([s["n"] for s in summaries])])
    n = min(a.n, int(starts[-1]))
    _check_sheet(n, a.tile, 6)
    picks = np.linspace(0, starts[-1] - 1, n).round().astype(int) if n > 0 else np.zeros(0, int)
    of_file = np.searchsorted(starts, picks, side="right") - 1
    tiles = []
    for k in np.unique(of_file):  # each file opened once, its picked rows read in order
        rows, s = picks[of_file == k] - starts[k], summaries[k]
        for row, bgr in zip(rows, read_patches(files[k], rows)):
            img = cv2.resize(np.ascontiguousarray(bgr[..., ::-1]), (a.tile, a.tile),
                             interpolation=cv2.INTER_AREA if a.tile < s["size"] else cv2.INTER_LINEAR)
            if s["gaze"] is not None:
                gaze_arrow(img, np.array([a.tile / 2, a.tile / 2]), s["gaze"][row], a.tile * 0.3)
            tiles.append(img)
    write_sheet(tiles, sheet, tile=a.tile)
    print(f"contact sheet: {sheet} ({n} face patches: normalized-camera gaze arrows from the centre)")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    ap = CliParser(prog="python -m train.data", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("synth", help="write synthetic subject files (HDF5) and split.json")
    s.add_argument("--subjects", type=int, default=8)
    s.add_argument("--frames", type=int, default=10, help="random gaze/pose/expression frames per subject")
    s.add_argument("--test-frames", type=int, default=None,
                   help="frames per held-out subject (the last quarter; default: --frames)")
    s.add_argument("--res", type=int, default=128, help="face-patch resolution (512 matches ETH-XGaze)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--light-jitter", type=float, default=0.6,
                   help="spread of the per-frame light direction (0: one frontal light for every frame)")
    s.add_argument("--scale", type=float, default=1.0,
                   help="head scale of every subject, in [0.5, 2] (x_world = scale R x_head + t, as real fits store)")
    s.add_argument("--out", default="data/synth")
    i = sub.add_parser("inspect", help="summary table and a contact sheet of subject files")
    i.add_argument("path", help="a subject .h5 file or a folder of them")
    i.add_argument("--sheet", default=None, help="contact sheet PNG path (default beside PATH)")
    i.add_argument("--n", type=int, default=18, help="images on the contact sheet")
    i.add_argument("--tile", type=int, default=160)
    i.add_argument("--layout", default="auto", choices=["auto", "ditgaze", "gazegaussian", "gazenerf", "xgaze"],
                   help="the files' layout (docs/data.md, Layouts); auto: detected from their keys")
    e = sub.add_parser("export", help="native subject files in a peer's layout (docs/data.md, Layouts)")
    e.add_argument("src", help="a folder of this project's subject files (its split.json decides the held-out ones)")
    e.add_argument("out", help="the folder to write (xgaze_<subject>.h5 and train_test_split.json)")
    e.add_argument("--layout", default="gazegaussian", choices=["gazegaussian", "ditgaze"])
    a = ap.parse_args(argv)
    if a.cmd == "export":
        return cmd_export(a)
    _check_flags(a)
    return cmd_synth(a) if a.cmd == "synth" else cmd_inspect(a)


def cmd_export(a) -> int:
    from train.data.export import export

    if Path(a.out).exists() and not Path(a.out).is_dir():
        raise ToolkitError(f"out {a.out}: is a file, expected a folder to write the exported files into")
    written = export(a.src, a.out, a.layout)
    print(f"wrote {len(written)} {a.layout} files and their split file to {a.out}")
    return 0


MAX_SHEET_IMAGES = 10_000
"""Images on one contact sheet (each is a sample read, drawn and kept until the sheet is encoded)."""

TILE_RANGE = (16, 4096)
"""Contact-sheet tile sides, pixels: smaller leaves no room for the drawn labels; larger only upscales."""


def _check_flags(a) -> None:
    """Every count and size flag bounded before any file is read or written, named as the user typed it."""
    if a.cmd == "synth":
        from train.data.generate import (
            MAX_FRAMES,
            MAX_SUBJECTS,
            RES_RANGE,
            SCALE_RANGE,
            SEED_RANGE,
            check_subject_memory,
        )

        check_count(a.subjects, "--subjects", 1, MAX_SUBJECTS, "a number of subject files")
        check_count(a.frames, "--frames", 1, MAX_FRAMES, "frames per subject")
        if a.test_frames is not None:
            check_count(a.test_frames, "--test-frames", 1, MAX_FRAMES, "frames per subject")
        check_count(a.res, "--res", *RES_RANGE, "an image size in pixels")
        check_count(a.seed, "--seed", *SEED_RANGE, "a seed")
        if not 0 <= a.light_jitter <= 2:  # NaN too
            raise ToolkitError(f"--light-jitter: expected a spread in [0, 2], got {a.light_jitter}")
        if not SCALE_RANGE[0] <= a.scale <= SCALE_RANGE[1]:  # NaN too
            raise ToolkitError(f"--scale: expected a head scale in [{SCALE_RANGE[0]}, {SCALE_RANGE[1]}], got {a.scale}")
        # One subject's images are held in memory until its file is written.
        for flag, frames in (("--frames", a.frames), ("--test-frames", a.test_frames if a.subjects > 1 else None)):
            if frames is not None:
                check_subject_memory(frames, a.res, f"one subject of {flag} {frames} x 18 cameras at --res {a.res}",
                                     hint="lower --frames or --res")
    else:
        check_count(a.n, "--n", 1, MAX_SHEET_IMAGES, "a number of images")
        check_count(a.tile, "--tile", *TILE_RANGE, "a tile side in pixels")


if __name__ == "__main__":
    sys.exit(run_cli(main))
