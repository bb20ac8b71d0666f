"""dlib's face-recognition embedding (the optional extra ``identity``) on faces aligned with given landmarks."""

import sys

import numpy as np
import pytest
import torch

from toolkit.errors import ToolkitError
from train.losses.face_embedding import SAME_PERSON_DISTANCE, FaceEmbedding, load_face_embedding

# iBUG-68 landmarks (x, y pixels) of scikit-image's two face photos, from apps.photo's face mesh (mediapipe).
ASTRONAUT_68 = [
    179, 102, 179, 111, 180, 130, 182, 141, 186, 150, 190, 157, 201, 168, 213, 175, 222, 177, 231, 176, 243, 170, 256,
    160, 261, 153, 265, 145, 268, 134, 271, 115, 271, 106, 187, 91, 191, 88, 198, 86, 206, 88, 215, 90, 235, 91, 244,
    90, 252, 90, 259, 92, 262, 95, 224, 100, 224, 110, 223, 120, 223, 126, 210, 129, 217, 132, 223, 133, 229, 132, 237,
    130, 195, 100, 202, 97, 206, 98, 213, 103, 206, 104, 200, 104, 236, 105, 244, 100, 248, 100, 256, 104, 250, 106,
    243, 106, 202, 139, 207, 139, 217, 139, 223, 140, 230, 139, 240, 140, 245, 140, 239, 149, 229, 155, 222, 155, 216,
    154, 207, 148, 203, 140, 213, 141, 223, 143, 234, 142, 243, 141, 233, 148, 223, 150, 213, 148]
CAMERAMAN_68 = [
    203, 143, 201, 148, 200, 161, 202, 169, 207, 175, 213, 180, 224, 186, 233, 189, 238, 189, 240, 188, 240, 184, 238,
    178, 237, 173, 236, 168, 236, 162, 238, 151, 240, 146, 223, 140, 228, 140, 234, 139, 240, 140, 246, 142, 252, 142,
    254, 142, 255, 142, 254, 143, 253, 145, 249, 149, 252, 155, 254, 161, 255, 165, 242, 167, 247, 168, 249, 168, 250,
    168, 251, 166, 228, 145, 234, 145, 236, 145, 239, 147, 236, 148, 233, 147, 249, 150, 251, 148, 253, 148, 253, 149,
    253, 150, 251, 150, 236, 179, 240, 178, 245, 175, 247, 175, 249, 175, 249, 177, 248, 178, 248, 180, 246, 182, 245,
    183, 243, 183, 238, 181, 237, 179, 242, 179, 246, 178, 247, 178, 247, 178, 247, 179, 245, 179, 242, 179]


@pytest.fixture(scope="module")
def embedding():
    pytest.importorskip("dlib", reason="the optional extra 'identity' (make setup installs it)")
    return FaceEmbedding()


def _lm(flat, shift=(0, 0)) -> torch.Tensor:
    return (torch.tensor(flat, dtype=torch.float32).view(1, 68, 2) + torch.tensor(shift, dtype=torch.float32))


def _img(rgb: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].float() / 255


def test_one_person_reads_close_and_two_people_far(embedding):
    """Real photos: the astronaut against a softened copy of herself (dlib's same-person range) and against the
    cameraman (beyond it)."""
    skimage_data = pytest.importorskip("skimage.data")
    import torch.nn.functional as F

    astro = _img(skimage_data.astronaut())
    soft = F.interpolate(F.interpolate(astro, size=(128, 128), mode="area"), size=(512, 512), mode="bilinear")
    camera = _img(np.repeat(skimage_data.camera()[..., None], 3, 2))
    lm_a, lm_c = _lm(ASTRONAUT_68), _lm(CAMERAMAN_68)
    same = float(embedding.distance(astro, lm_a, soft, lm_a)[0])
    other = float(embedding.distance(astro, lm_a, camera, lm_c)[0])
    assert same < SAME_PERSON_DISTANCE < other, (same, other)
    assert other - same > 0.3
    moved = torch.roll(astro, (-5, 7), dims=(2, 3))  # 7 px right, 5 up: the landmarks move with the face
    assert float(embedding.distance(astro, lm_a, moved, _lm(ASTRONAUT_68, (7, -5)))[0]) < 0.05


def test_the_same_face_is_at_distance_zero(embedding):
    g = torch.Generator().manual_seed(0)
    img = torch.rand(2, 3, 96, 112, generator=g)
    lm = _lm(ASTRONAUT_68, (-170, -70)).repeat(2, 1, 1) * 0.8
    e = embedding.embed(img, lm)
    assert e.shape == (2, 128) and e.dtype == torch.float32 and torch.isfinite(e).all()
    assert torch.equal(embedding.distance(img, lm, img, lm), torch.zeros(2))
    assert float(embedding.distance(img[:1], lm[:1], torch.rand(1, 3, 96, 112, generator=g), lm[:1])[0]) > 0.01


def test_bad_inputs_are_one_line_errors(embedding):
    img, lm = torch.rand(1, 3, 32, 32), _lm(ASTRONAUT_68, (-170, -70)) * 0.2
    for bad_img, bad_lm, match in ((img[:, :2], lm, r"\[B, 3, H, W\]"), (img, lm[:, :5], r"\[1, 68, 2\]"),
                                   (img * float("nan"), lm, "finite"), (img, lm * float("inf"), "finite"),
                                   (img, torch.full_like(lm, 5.0), "spread"), (img, lm + 1e7, "within")):
        with pytest.raises(ToolkitError, match=match):
            embedding.embed(bad_img, bad_lm)
    with pytest.raises(ToolkitError, match="pairs"):
        embedding.distance(img, lm, img.repeat(2, 1, 1, 1), lm.repeat(2, 1, 1))
    assert embedding.embed(img[:0], lm[:0]).shape == (0, 128)


def test_stress_odd_images_and_landmarks_give_finite_embeddings(embedding):
    """Tiny images, faces mostly outside them, values outside [0, 1], landmarks far off: finite embeddings."""
    g = torch.Generator().manual_seed(1)
    base = _lm(ASTRONAUT_68, (-225, -130))
    for h, w, scale, shift, lo, hi in ((4, 4, 0.05, (2, 2), 0, 1), (17, 9, 0.5, (-30, 40), -3, 4),
                                       (64, 64, 5.0, (900, -900), 0, 1), (40, 70, 0.3, (20, 35), 0, 1)):
        img = lo + (hi - lo) * torch.rand(2, 3, h, w, generator=g)
        lm = base.repeat(2, 1, 1) * scale + torch.tensor(shift, dtype=torch.float32)
        e = embedding.embed(img, lm)
        assert e.shape == (2, 128) and torch.isfinite(e).all()


def test_without_the_extra_the_embedding_names_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "dlib", None)  # import dlib -> ImportError
    with pytest.raises(ToolkitError, match=r"pip install 'ditgaze\[identity\]'"):
        FaceEmbedding()
    lines = []
    assert load_face_embedding(log=lines.append) is None
    assert len(lines) == 1 and "identity drift: n/a" in lines[0] and "ditgaze[identity]" in lines[0]


def test_identity_scores_of_the_protocol(embedding):
    """The protocol's per-pair identity scores: ArcFace input <-> render (an untrained backbone here) and the
    dlib drift input -> render with its floor input -> target; a render that is the input scores 1 and 0."""
    from train.evaluation.protocol import _identity_scores
    from train.losses.identity import IdentitySimilarity

    g = torch.Generator().manual_seed(2)
    inp, tgt = torch.rand(2, 3, 64, 64, generator=g), torch.rand(2, 3, 64, 64, generator=g)
    lm = (_lm(ASTRONAUT_68, (-225, -130)) * 0.5 + 32).repeat(2, 1, 1)
    arcface = IdentitySimilarity(arch="iresnet18")
    s = _identity_scores(arcface, embedding, inp, lm, inp, tgt, lm)
    assert torch.allclose(s["identity_similarity_input"], torch.ones(2), atol=1e-5)
    assert torch.equal(s["identity_drift"], torch.zeros(2)) and bool((s["identity_drift_real"] > 0).all())
    assert torch.allclose(s["identity_similarity"], arcface(inp, tgt, lm))
    assert set(_identity_scores(None, None, inp, lm, inp, tgt, lm).values()) == {None}
