"""ArcFace identity similarity: insightface's key names, an explicit re-computation of the backbone, the five-point
alignment, metric properties, weight files, input checks, stress."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from tests.train.helpers import save_state_file
from toolkit.errors import ToolkitError
from train.losses.identity import (
    ARCFACE_TEMPLATE,
    IdentitySimilarity,
    IResNet,
    align_faces,
    arcface_transform,
    five_point_landmarks,
    load_identity_model,
)

# insightface ``recognition/arcface_torch/backbones/iresnet.py``, written out so the tests owe nothing to the module:
# blocks per stage, and each stage's (in, out) channels; every stage's first block has stride 2 and a downsample.
BLOCKS = {"iresnet18": (2, 2, 2, 2), "iresnet34": (3, 4, 6, 3), "iresnet50": (3, 4, 14, 3),
          "iresnet100": (3, 13, 30, 3)}
STAGES = ((64, 64), (64, 128), (128, 256), (256, 512))
BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
TEMPLATE = torch.tensor(ARCFACE_TEMPLATE, dtype=torch.float64)


def _bn(prefix, c):
    return {f"{prefix}.{s}": (() if s == "num_batches_tracked" else (c,)) for s in BN}


def insightface_keys(arch="iresnet18"):
    """Ordered {name: shape} of insightface's IResNet state dict (its module registration order)."""
    keys = {"conv1.weight": (64, 3, 3, 3), **_bn("bn1", 64), "prelu.weight": (64,)}
    for s, ((c_in, c_out), n) in enumerate(zip(STAGES, BLOCKS[arch])):
        for i in range(n):
            p, cin = f"layer{s + 1}.{i}", (c_in if i == 0 else c_out)
            keys.update({**_bn(f"{p}.bn1", cin), f"{p}.conv1.weight": (c_out, cin, 3, 3), **_bn(f"{p}.bn2", c_out),
                         f"{p}.prelu.weight": (c_out,), f"{p}.conv2.weight": (c_out, c_out, 3, 3),
                         **_bn(f"{p}.bn3", c_out)})
            if i == 0:
                keys.update({f"{p}.downsample.0.weight": (c_out, c_in, 1, 1), **_bn(f"{p}.downsample.1", c_out)})
    keys.update({**_bn("bn2", 512), "fc.weight": (512, 512 * 7 * 7), "fc.bias": (512,), **_bn("features", 512)})
    return keys


def _random_state(seed=0):
    """Random iresnet18 weights in insightface's naming, scaled so activations stay O(1) and images differ."""
    g = torch.Generator().manual_seed(seed)
    state = {}
    for name, shape in insightface_keys().items():
        leaf = name.rsplit(".", 1)[-1]
        if leaf == "num_batches_tracked":
            state[name] = torch.tensor(1000)
        elif name.endswith("conv1.weight") or name.endswith("conv2.weight") or ".downsample.0." in name:
            fan_in = shape[1] * shape[2] * shape[3]
            state[name] = torch.randn(shape, generator=g) * (1.0 / fan_in) ** 0.5
        elif name == "fc.weight":
            state[name] = torch.randn(shape, generator=g) * (1.0 / shape[1]) ** 0.5
        elif name == "features.weight":
            state[name] = torch.ones(shape)  # frozen at 1 in the reference
        elif leaf == "weight" and "prelu" in name:
            state[name] = 0.25 + 0.05 * torch.randn(shape, generator=g)
        elif leaf == "weight":
            state[name] = 1 + 0.1 * torch.randn(shape, generator=g)
        elif leaf == "running_var":
            state[name] = 0.5 + torch.rand(shape, generator=g)
        else:  # BN bias, running_mean, fc.bias
            state[name] = 0.1 * torch.randn(shape, generator=g)
    return state


def _reference_embedding(state, x):
    """insightface's IResNet.forward written out functionally, in float64, on an already-scaled input."""
    sd = {k: v.double() for k, v in state.items()}

    def bn(p, y):
        return F.batch_norm(y, sd[f"{p}.running_mean"], sd[f"{p}.running_var"], sd[f"{p}.weight"],
                            sd[f"{p}.bias"], training=False, eps=1e-5)

    y = F.prelu(bn("bn1", F.conv2d(x.double(), sd["conv1.weight"], padding=1)), sd["prelu.weight"])
    for s, n in enumerate(BLOCKS["iresnet18"]):
        for i in range(n):
            p, stride = f"layer{s + 1}.{i}", (2 if i == 0 else 1)
            out = F.conv2d(bn(f"{p}.bn1", y), sd[f"{p}.conv1.weight"], padding=1)
            out = F.prelu(bn(f"{p}.bn2", out), sd[f"{p}.prelu.weight"])
            out = bn(f"{p}.bn3", F.conv2d(out, sd[f"{p}.conv2.weight"], stride=stride, padding=1))
            if i == 0:
                y = bn(f"{p}.downsample.1", F.conv2d(y, sd[f"{p}.downsample.0.weight"], stride=2))
            y = out + y
    y = F.linear(torch.flatten(bn("bn2", y), 1), sd["fc.weight"], sd["fc.bias"])
    return bn("features", y)


def _landmarks(five, seed=0):
    """[B, 68, 2] iBUG landmarks whose five ArcFace points are exactly ``five`` [B, 5, 2]: six eye points on a
    circle around each eye centre (so their mean is the centre), the other 52 points random."""
    five = torch.as_tensor(five, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    lm = five[:, 2:3] + 20 * torch.randn(five.shape[0], 68, 2, generator=g, dtype=torch.float64)
    ang = torch.arange(6, dtype=torch.float64) * (math.pi / 3)
    ring = 3 * torch.stack([ang.cos(), ang.sin()], -1)
    lm[:, 36:42] = five[:, 0:1] + ring
    lm[:, 42:48] = five[:, 1:2] + ring
    lm[:, 30], lm[:, 48], lm[:, 54] = five[:, 2], five[:, 3], five[:, 4]
    return lm


def _similarity(scale, angle_deg, centre):
    """[2, 3] crop-pixels -> image-pixels similarity sending the template's centroid to ``centre``."""
    a = math.radians(angle_deg)
    rot = scale * torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=torch.float64)
    t = torch.tensor(centre, dtype=torch.float64) - rot @ TEMPLATE.mean(0)
    return torch.cat([rot, t[:, None]], 1)


def _apply(m, pts):
    return pts @ m[:, :2].T + m[:, 2]


def _face_images(b=2, h=96, w=80, seed=0):
    """Two random image batches and landmarks of a face roughly filling them."""
    g = torch.Generator().manual_seed(seed)
    five = torch.stack([_apply(_similarity(0.6 + 0.1 * i, 10 * i - 5, (w / 2, h / 2)), TEMPLATE) for i in range(b)])
    return (torch.rand(b, 3, h, w, generator=g), torch.rand(b, 3, h, w, generator=g),
            _landmarks(five, seed).float())


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("identity")
    state = _random_state()
    nested = {"state_dict": {f"module.{k}": v for k, v in state.items()}, "epoch": 3}
    return {
        "state": state,
        "pth": save_state_file(d / "backbone.pth", state),
        "nested": save_state_file(d / "nested.pt", nested),
        "model": save_state_file(d / "model.pth", {"model": state}),
        "safetensors": save_state_file(d / "backbone.safetensors", state),
        "no_counters": save_state_file(d / "no_counters.pth",
                             {k: v for k, v in state.items() if not k.endswith("num_batches_tracked")}),
    }


@pytest.fixture(scope="module")
def model(files):
    return load_identity_model(files["pth"], arch="iresnet18")


# ----------------------------------------------------------------------------- architecture and key names
@pytest.mark.parametrize("arch", list(BLOCKS))
def test_state_dict_keys_and_shapes_are_insightfaces(arch):
    own = {k: tuple(v.shape) for k, v in IResNet(arch).state_dict().items()}
    assert own == insightface_keys(arch)
    assert list(own) == list(insightface_keys(arch))  # and in the reference's registration order
    assert len(own) == 19 + 18 * sum(BLOCKS[arch]) + 6 * 4


def test_iresnet18_spot_keys():
    own = {k: tuple(v.shape) for k, v in IResNet("iresnet18").state_dict().items()}
    assert own["prelu.weight"] == (64,)
    assert own["layer1.0.downsample.0.weight"] == (64, 64, 1, 1)  # layer1 downsamples too (stride 2)
    assert own["layer2.0.downsample.0.weight"] == (128, 64, 1, 1)
    assert own["layer2.0.bn1.weight"] == (64,) and own["layer2.0.conv2.weight"] == (128, 128, 3, 3)
    assert own["layer4.1.bn3.running_var"] == (512,)
    assert "layer1.1.downsample.0.weight" not in own and "layer4.2.bn1.weight" not in own
    assert own["fc.weight"] == (512, 25088) and own["features.running_mean"] == (512,)
    assert len(own) == 187


def test_backbone_matches_explicit_reference(files, model):
    g = torch.Generator().manual_seed(1)
    crop = torch.rand(1, 3, 112, 112, generator=g)
    ref = _reference_embedding(files["state"], 2 * crop.double() - 1)
    with torch.no_grad():
        got = model.embed(crop)
        got64 = load_identity_model(files["pth"], "iresnet18").double().embed(crop.double())
    assert got.shape == (1, 512) and got.dtype == torch.float32
    assert float(ref.abs().max()) > 1e-2
    torch.testing.assert_close(got.double(), ref, rtol=1e-4, atol=1e-4 * float(ref.abs().max()))
    torch.testing.assert_close(got64, ref, rtol=1e-9, atol=1e-10)


# ----------------------------------------------------------------------------- alignment
def test_five_points_are_the_ibug_eye_means_nose_and_mouth_corners():
    g = torch.Generator().manual_seed(2)
    lm = torch.rand(3, 68, 2, generator=g) * 100
    five = five_point_landmarks(lm)
    torch.testing.assert_close(five[:, 0], lm[:, 36:42].mean(1))
    torch.testing.assert_close(five[:, 1], lm[:, 42:48].mean(1))
    assert torch.equal(five[:, 2], lm[:, 30]) and torch.equal(five[:, 3], lm[:, 48])
    assert torch.equal(five[:, 4], lm[:, 54])


def test_landmarks_on_the_template_give_the_identity():
    lm = _landmarks(TEMPLATE[None])
    m = arcface_transform(lm)
    torch.testing.assert_close(m[0], torch.eye(2, 3, dtype=torch.float64), rtol=0, atol=1e-12)
    img = torch.rand(1, 3, 112, 112, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(align_faces(img, lm.float()), img, rtol=0, atol=1e-4)  # float32 grid rounding
    torch.testing.assert_close(align_faces(img.double(), lm), img.double(), rtol=0, atol=1e-10)


@pytest.mark.parametrize("scale, angle, centre", [(1.7, 25.0, (150.0, 140.0)), (0.45, -160.0, (30.0, 50.0))])
def test_known_similarity_is_inverted(scale, angle, centre):
    s = _similarity(scale, angle, centre)  # crop -> image
    m = arcface_transform(_landmarks(_apply(s, TEMPLATE)[None]))[0]  # image -> crop
    composed = m[:, :2] @ s[:, :2], m[:, :2] @ s[:, 2] + m[:, 2]
    torch.testing.assert_close(composed[0], torch.eye(2, dtype=torch.float64), rtol=0, atol=1e-10)
    torch.testing.assert_close(composed[1], torch.zeros(2, dtype=torch.float64), rtol=0, atol=1e-8)


def test_bright_dots_at_the_landmarks_land_on_the_template():
    """Gaussian dots at a scaled, rotated, shifted copy of the template in a 300x300 black image: after alignment
    each dot's centroid sits on its template point (pixel centres at integers, as cv2.warpAffine)."""
    scale = 1.7
    s = _similarity(scale, 25.0, (152.0, 147.0))
    src = _apply(s, TEMPLATE)
    ys, xs = torch.meshgrid(torch.arange(300.0), torch.arange(300.0), indexing="ij")
    sigma = 1.5 * scale
    img = sum(torch.exp(-((xs - x) ** 2 + (ys - y) ** 2) / (2 * sigma ** 2)) for x, y in src.float())
    aligned = align_faces(img.expand(1, 3, 300, 300).contiguous(), _landmarks(src[None]).float())[0, 0]
    assert aligned.shape == (112, 112)
    for tx, ty in ARCFACE_TEMPLATE:
        cx, cy, r = round(tx), round(ty), 6
        win = aligned[cy - r:cy + r + 1, cx - r:cx + r + 1].double()
        yy, xx = torch.meshgrid(torch.arange(cy - r, cy + r + 1.0), torch.arange(cx - r, cx + r + 1.0), indexing="ij")
        got = ((win * xx).sum() / win.sum(), (win * yy).sum() / win.sum())
        assert abs(float(got[0]) - tx) < 0.1 and abs(float(got[1]) - ty) < 0.1, (tx, ty, got)
        assert float(win.max()) > 0.8  # the dot, not a neighbour's tail


def _umeyama(src, dst):
    """Umeyama (1991) least-squares similarity src -> dst with the reflection fix, as skimage's estimate."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    sc, dc = src - mu_s, dst - mu_d
    cov = dc.T @ sc / len(src)
    u, d, vt = np.linalg.svd(cov)
    fix = np.diag([1.0, -1.0 if np.linalg.det(cov) < 0 else 1.0])
    rot = u @ fix @ vt
    c = np.trace(np.diag(d) @ fix) / (sc ** 2).sum(1).mean()
    return np.concatenate([c * rot, (mu_d - c * rot @ mu_s)[:, None]], 1)


def test_noisy_and_mirrored_landmarks_match_umeyama_without_reflection():
    g = torch.Generator().manual_seed(4)
    five = torch.stack([_apply(_similarity(0.8 + 0.3 * i, 40.0 * i, (100.0, 90.0)), TEMPLATE) for i in range(4)])
    five = five + 3 * torch.randn(five.shape, generator=g, dtype=torch.float64)
    five[3, :, 0] = 200 - five[3, :, 0]  # a mirror image: the best fit would reflect; it must not
    m = arcface_transform(_landmarks(five))
    for i in range(4):
        ref = _umeyama(five[i].numpy(), TEMPLATE.numpy())
        np.testing.assert_allclose(m[i].numpy(), ref, rtol=0, atol=1e-9)
        assert float(torch.linalg.det(m[i, :, :2])) > 0


def test_outside_the_image_is_white():
    img = torch.zeros(1, 3, 40, 40)
    five = _apply(_similarity(2.0, 0.0, (20.0, 20.0)), TEMPLATE)  # a face twice the crop's: it reaches past the image
    out = align_faces(img, _landmarks(five[None]).float())
    # The image lands on crop pixels x in [46, 66], y in [62, 82] (around the template's centroid (56, 72)).
    assert float(out[0, :, :5, :5].min()) == 1.0 and float(out[0, :, 100:, 100:].min()) == 1.0
    assert float(out[0, :, 65:80, 50:62].max()) == 0.0


# ----------------------------------------------------------------------------- metric properties
def test_self_similarity_is_one_range_and_symmetry(model):
    a, b, lm = _face_images()
    with torch.no_grad():
        s_aa, s_ab, s_ba = model(a, a, lm), model(a, b, lm), model(b, a, lm)
    assert s_aa.shape == (2,) and s_aa.dtype == torch.float32
    torch.testing.assert_close(s_aa, torch.ones(2), rtol=0, atol=1e-5)
    assert bool((s_ab >= -1).all() and (s_ab <= 1).all()) and bool((s_ab < 1 - 1e-4).all())
    torch.testing.assert_close(s_ab, s_ba, rtol=0, atol=1e-6)
    assert float(model(a, a.clone(), lm).min()) > 1 - 1e-5


def test_similarity_is_the_cosine_of_the_aligned_embeddings(model):
    a, b, lm = _face_images(seed=5)
    with torch.no_grad():
        ea, eb = model.embed(align_faces(a, lm)), model.embed(align_faces(b, lm))
        torch.testing.assert_close(model(a, b, lm), F.cosine_similarity(ea, eb), rtol=0, atol=1e-5)


def test_batch_entries_are_independent(model):
    a, b, lm = _face_images(b=3, seed=6)
    with torch.no_grad():
        batch = model(a, b, lm)
        single = torch.cat([model(a[i:i + 1], b[i:i + 1], lm[i:i + 1]) for i in range(3)])
    torch.testing.assert_close(batch, single, rtol=0, atol=1e-5)


def test_frozen_eval_and_gradients_reach_the_images(model):
    model.train()
    assert not model.training and not model.backbone.training
    assert not any(p.requires_grad for p in model.parameters())
    a, b, lm = _face_images(b=1, seed=7)
    a.requires_grad_(True)
    model(a, b, lm).sum().backward()
    assert torch.isfinite(a.grad).all() and float(a.grad.abs().sum()) > 0
    assert all(p.grad is None for p in model.parameters())


# ----------------------------------------------------------------------------- weight files
@pytest.mark.parametrize("key", ["pth", "nested", "model", "safetensors", "no_counters"])
def test_every_layout_and_format_loads_the_same_weights(files, key):
    m = load_identity_model(files[key], arch="iresnet18")
    assert isinstance(m, IdentitySimilarity) and not m.training
    assert not any(p.requires_grad for p in m.parameters())
    own = m.backbone.state_dict()
    for name, v in files["state"].items():
        if key == "no_counters" and name.endswith("num_batches_tracked"):
            continue
        assert torch.equal(own[name].to(v.dtype), v), name
        assert own[name].dtype in (torch.float32, torch.int64)


def _bad_file(path, case, state):
    if case == "garbage":
        path.write_bytes(b"\x00not a weights file\xff" * 8)
    elif case == "not a dict":
        torch.save(torch.zeros(3), path)
    elif case == "missing key":
        save_state_file(path, {k: v for k, v in state.items() if k != "layer3.1.bn2.running_var"})
    elif case == "wrong shape":
        save_state_file(path, {**state, "layer2.0.conv1.weight": torch.zeros(128, 32, 3, 3)})
    elif case == "nan":
        save_state_file(path, {**state, "fc.bias": torch.full((512,), float("nan"))})
    elif case == "deeper file":
        save_state_file(path, {**state, "layer1.2.bn1.weight": torch.ones(64), "layer1.2.bn1.bias": torch.zeros(64)})
    elif case == "other arch":
        save_state_file(path, state)
    return path


@pytest.mark.parametrize("case, ext, match", [
    ("missing file", ".pth", "no such ArcFace backbone weights file"),
    ("garbage", ".pth", "weights-only"),
    ("garbage", ".safetensors", "not a valid safetensors"),
    ("not a dict", ".pth", "expected a state dict"),
    ("missing key", ".pth", r"missing tensor 'layer3\.1\.bn2\.running_var'"),
    ("missing key", ".safetensors", r"missing tensor 'layer3\.1\.bn2\.running_var'"),
    ("wrong shape", ".pth", r"'layer2\.0\.conv1\.weight' has shape \[128, 32, 3, 3\], expected \[128, 64, 3, 3\]"),
    ("nan", ".pth", r"'fc\.bias' must be finite"),
    ("deeper file", ".pth", r"unexpected tensor 'layer1\.2\.bn1\."),
    ("other arch", ".pth", r"missing tensor 'layer1\.2\..*are iresnet18's, pass arch='iresnet18'"),
])
def test_bad_files_give_one_line_errors_naming_the_file(files, tmp_path, case, ext, match):
    bad = tmp_path / f"bad{ext}"
    if case != "missing file":
        _bad_file(bad, case, files["state"])
    arch = "iresnet34" if case == "other arch" else "iresnet18"
    with pytest.raises(ToolkitError, match=match) as info:
        load_identity_model(bad, arch=arch)
    msg = str(info.value)
    assert "\n" not in msg and str(bad) in msg


def test_unknown_arch_is_named():
    with pytest.raises(ToolkitError, match="iresnet42.*iresnet18, iresnet34, iresnet50, iresnet100"):
        IResNet("iresnet42")


# ----------------------------------------------------------------------------- inputs
def _bad_inputs(case):
    a, b, lm = _face_images(b=2, seed=8)
    if case == "nan a":
        a[0, 1, 3, 4] = float("nan")
    elif case == "inf b":
        b[1, 0, 0, 0] = float("inf")
    elif case == "no batch":
        a, b = a[0], b[0]
    elif case == "gray":
        a, b = a[:, :1], b[:, :1]
    elif case == "shapes differ":
        b = b[:, :, :-1]
    elif case == "uint8":
        a, b = (a * 255).to(torch.uint8), (b * 255).to(torch.uint8)
    elif case == "five points":
        lm = five_point_landmarks(lm)
    elif case == "xyz landmarks":
        lm = torch.cat([lm, lm[..., :1]], -1)
    elif case == "landmark batch":
        lm = lm[:1]
    elif case == "nan landmarks":
        lm[1, 30, 0] = float("nan")
    elif case == "degenerate":
        lm = torch.full_like(lm, 17.0)
    elif case == "collapsed fit":
        # Five points orthogonal (as complex vectors) to the template's: the best similarity is zero.
        q = torch.complex(TEMPLATE[:, 0], TEMPLATE[:, 1])
        q = q - q.mean()
        z = torch.complex(*torch.randn(2, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(9)))
        z = z - z.mean()
        z = 20 * (z - (q.conj() * z).sum() / (q.conj() * q).sum() * q) + 40
        lm = _landmarks(torch.stack([z.real, z.imag], -1).expand(2, 5, 2))  # float64: keep the fit exactly 0
    return a, b, lm


@pytest.mark.parametrize("case, match", [
    ("nan a", "input a contains NaN or inf"),
    ("inf b", "input b contains NaN or inf"),
    ("no batch", r"input a must be a \[B, 3, H, W\]"),
    ("gray", r"input a must be a \[B, 3, H, W\]"),
    ("shapes differ", "one shape"),
    ("uint8", "floating-point"),
    ("five points", r"landmarks must be a \[B, 68, 2\].*got \[2, 5, 2\]"),
    ("xyz landmarks", r"landmarks must be a \[B, 68, 2\].*got \[2, 68, 3\]"),
    ("landmark batch", r"landmarks must be a \[B, 68, 2\].*B = 2, got \[1, 68, 2\]"),
    ("nan landmarks", "landmarks contain NaN or inf"),
    ("degenerate", "landmarks of batch entry 0 are degenerate"),
    ("collapsed fit", "landmarks of batch entry 0 do not fit a face"),
])
def test_bad_inputs_raise_one_line_errors(model, case, match):
    a, b, lm = _bad_inputs(case)
    with pytest.raises(ToolkitError, match=match) as info:
        model(a, b, lm)
    assert "\n" not in str(info.value)


def test_align_faces_checks_its_arguments():
    with pytest.raises(ToolkitError, match=r"input images must be a \[B, 3, H, W\]"):
        align_faces(torch.rand(3, 32, 32), torch.rand(1, 68, 2))
    with pytest.raises(ToolkitError, match="landmarks of batch entry 1 are degenerate"):
        lm = _landmarks(TEMPLATE[None].expand(2, 5, 2)).float()
        lm[1] = 5.0
        align_faces(torch.rand(2, 3, 112, 112), lm)


def test_empty_batch(model):
    assert model(torch.rand(0, 3, 32, 32), torch.rand(0, 3, 32, 32), torch.rand(0, 68, 2)).shape == (0,)


# ----------------------------------------------------------------------------- stress
def _stress_inputs(case):
    a, b, lm = _face_images(b=2, seed=10)
    if case == "constant":
        return torch.full_like(a, 0.5), torch.full_like(b, 0.25), lm
    if case == "all white":
        return torch.ones_like(a), torch.ones_like(b), lm
    if case == "landmarks far outside":
        return a, b, lm * 1e3 + torch.tensor([1e7, -3e6])
    if case == "landmarks tiny and off-image":
        return a, b, (lm - lm.mean(1, keepdim=True)) * 1e-3 - 50
    if case == "tiny 32x32":
        return a[..., :32, :32].contiguous(), b[..., :32, :32].contiguous(), lm * (32 / 96)
    return a, b, lm


@pytest.mark.parametrize("case", ["constant", "all white", "landmarks far outside", "landmarks tiny and off-image",
                                  "tiny 32x32"])
@pytest.mark.parametrize("identical", [False, True])
def test_extreme_inputs_give_finite_similarities_and_gradients(model, case, identical):
    a, b, lm = _stress_inputs(case)
    a.requires_grad_(True)
    if identical:
        b = a
    else:
        b.requires_grad_(True)
    s = model(a, b, lm)
    assert s.shape == (2,) and torch.isfinite(s).all() and bool((s.abs() <= 1).all())
    s.sum().backward()
    assert torch.isfinite(a.grad).all()
    if identical:
        torch.testing.assert_close(s.detach(), torch.ones(2), rtol=0, atol=1e-5)
    else:
        assert torch.isfinite(b.grad).all()
