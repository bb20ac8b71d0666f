"""apps.photo.paste.paste_back: a normalized crop pasted back into its photo."""

import cv2
import h5py
import numpy as np
import pytest

from apps.photo.normalize import to_opencv
from apps.photo.paste import feathered_alpha, paste_back


def _psnr(a, b):
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    pytest.importorskip("mediapipe")
    skdata = pytest.importorskip("skimage.data")
    from apps import prepare

    d = tmp_path_factory.mktemp("paste")
    photo = np.ascontiguousarray(skdata.astronaut()[..., ::-1])
    cv2.imwrite(str(d / "astronaut.png"), photo)
    assert prepare.main([str(d / "astronaut.png"), "--out", str(d / "out")]) == 0
    with h5py.File(d / "out" / "astronaut.h5") as f:
        row = {k: f[k][0] for k in ("face_patch", "head_mask", "warp")}
    return photo, row


def _inside_and_outside(photo_shape, row, S, feather):
    """Photo pixels whose crop sample lies where the feathered alpha is 1 (inside) and where the mask, dilated by a
    pixel, is 0 or the crop is not (outside)."""
    W = row["warp"].astype(np.float64) * np.array([[S / 512], [S / 512], [1.0]])
    alpha = feathered_alpha(row["head_mask"] if S == 512 else cv2.resize(row["head_mask"], (S, S),
                                                                            interpolation=cv2.INTER_NEAREST), feather)
    dil = cv2.dilate((alpha > 0).astype(np.uint8), np.ones((5, 5), np.uint8))
    H, Wd = photo_shape[:2]
    samp = lambda m: cv2.warpPerspective(m, to_opencv(W), (Wd, H), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP)  # noqa: E731
    inside = samp(cv2.erode((alpha >= 0.999).astype(np.uint8), np.ones((5, 5), np.uint8))) > 0
    outside = samp(np.ones((S, S), np.uint8) - dil) > 0
    covered = samp(np.ones((S, S), np.uint8)) > 0
    return inside, outside | ~covered


def test_an_unchanged_crop_pasted_back_reproduces_the_face_and_leaves_the_rest(prepared):
    photo, row = prepared
    out = paste_back(photo, row["face_patch"], row["head_mask"], row["warp"])
    inside, outside = _inside_and_outside(photo.shape, row, 512, 0.02 * 512)
    assert inside.sum() > 3000
    assert _psnr(out[inside], photo[inside]) > 35
    assert np.array_equal(out[outside], photo[outside])  # bit for bit
    assert out.dtype == np.uint8 and out.shape == photo.shape


def test_a_crop_of_another_size_is_the_same_square(prepared):
    """A redirected crop at the run's resolution (128 here) pastes with the prepared file's warp and size."""
    photo, row = prepared
    small = cv2.resize(row["face_patch"], (128, 128), interpolation=cv2.INTER_AREA)
    mask = cv2.resize(row["head_mask"], (128, 128), interpolation=cv2.INTER_NEAREST)
    out = paste_back(photo, small, mask, row["warp"], warp_size=512)
    inside, outside = _inside_and_outside(photo.shape, row, 128, 0.02 * 128)
    assert _psnr(out[inside], photo[inside]) > 30  # the 128² crop holds less detail than the 92 px face had
    assert np.array_equal(out[outside], photo[outside])


def test_a_changed_crop_changes_only_the_head(prepared):
    photo, row = prepared
    grey = np.full_like(row["face_patch"], 128)
    out = paste_back(photo, grey, row["head_mask"], row["warp"], feather_px=0)
    changed = (out != photo).any(-1)
    inside, outside = _inside_and_outside(photo.shape, row, 512, 0)
    assert (out[inside] == 128).all() and not changed[outside].any()
