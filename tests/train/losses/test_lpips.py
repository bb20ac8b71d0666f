"""LPIPS-VGG: metric properties, an explicit re-computation, weight files, input checks, stress."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from tests.train.helpers import save_state_file
from toolkit.errors import ToolkitError
from train.losses.lpips import LPIPS, load_lpips

# torchvision VGG16 "D": the index in ``features`` of each conv (its ReLU is the next index), its channels,
# and whether a 2x2 max-pool follows the ReLU. Written out so the reference below owes nothing to the module.
CONVS = [(0, 3, 64, False), (2, 64, 64, True),
         (5, 64, 128, False), (7, 128, 128, True),
         (10, 128, 256, False), (12, 256, 256, False), (14, 256, 256, True),
         (17, 256, 512, False), (19, 512, 512, False), (21, 512, 512, True),
         (24, 512, 512, False), (26, 512, 512, False), (28, 512, 512, False)]
TAPS = (3, 8, 15, 22, 29)  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3
LIN_CHANNELS = (64, 128, 256, 512, 512)


def _vgg_state(seed=0):
    """Random He-scaled weights in torchvision's VGG16 layout, plus a classifier key that must be ignored."""
    g = torch.Generator().manual_seed(seed)
    state = {}
    for i, c_in, c_out, _ in CONVS:
        state[f"features.{i}.weight"] = torch.randn(c_out, c_in, 3, 3, generator=g) * (2 / (9 * c_in)) ** 0.5
        state[f"features.{i}.bias"] = torch.randn(c_out, generator=g) * 0.05
    state["classifier.0.weight"] = torch.zeros(4, 4)
    return state


def _lin_state(seed=1, official=True):
    g = torch.Generator().manual_seed(seed)
    infix = ".model.1" if official else ""
    return {f"lin{k}{infix}.weight": torch.rand(1, c, 1, 1, generator=g) for k, c in enumerate(LIN_CHANNELS)}


def _reference_lpips(vgg, lin, a, b):
    """LPIPS written out from the paper and the reference code, in float64."""
    vgg = {k: v.double() for k, v in vgg.items()}
    shift = torch.tensor([-0.030, -0.088, -0.188], dtype=torch.float64).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450], dtype=torch.float64).view(1, 3, 1, 1)

    def taps(x):
        x = (x.double() * 2 - 1 - shift) / scale
        out = []
        for i, _, _, pool in CONVS:
            x = torch.relu(F.conv2d(x, vgg[f"features.{i}.weight"], vgg[f"features.{i}.bias"], padding=1))
            if i + 1 in TAPS:
                out.append(x / (torch.sqrt((x ** 2).sum(1, keepdim=True)) + 1e-10))
            if pool:
                x = F.max_pool2d(x, 2, 2)
        return out

    total = 0
    for k, (x, y) in enumerate(zip(taps(a), taps(b))):
        w = lin[f"lin{k}.model.1.weight"].double()
        total = total + F.conv2d((x - y) ** 2, w).mean((1, 2, 3))
    return total


def _images(b=2, h=32, w=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, 3, h, w, generator=g), torch.rand(b, 3, h, w, generator=g)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """One random VGG16 and one random lin set, each written in every accepted layout and format."""
    d = tmp_path_factory.mktemp("lpips")
    vgg, lin = _vgg_state(), _lin_state()
    flat = {k.replace(".model.1", ""): v for k, v in lin.items()}
    return {
        "vgg_state": vgg,
        "lin_state": lin,
        "vgg.pth": save_state_file(d / "vgg16.pth", vgg),
        "vgg.safetensors": save_state_file(d / "vgg16.safetensors", vgg),
        "lin.pth": save_state_file(d / "lin.pth", lin),
        "lin.safetensors": save_state_file(d / "lin.safetensors", lin),
        "flat.pth": save_state_file(d / "lin_flat.pth", flat),
        "flat.safetensors": save_state_file(d / "lin_flat.safetensors", flat),
    }


@pytest.fixture(scope="module")
def model(files):
    return load_lpips(files["vgg.pth"], files["lin.pth"])


# ----------------------------------------------------------------------------- metric properties
def test_identity_positivity_symmetry_and_output_type(model):
    x, y = _images()
    with torch.no_grad():
        d_xx, d_xy, d_yx = model(x, x), model(x, y), model(y, x)
    assert d_xx.shape == (2,) and d_xx.dtype == torch.float32
    assert float(d_xx.abs().max()) < 1e-6
    assert bool((d_xy > 1e-3).all())
    torch.testing.assert_close(d_xy, d_yx, rtol=1e-6, atol=1e-7)
    assert float(model(x, x.clone()).abs().max()) < 1e-6


def test_batch_entries_are_independent(model):
    x, y = _images(b=3, seed=2)
    with torch.no_grad():
        batch = model(x, y)
        single = torch.cat([model(x[i:i + 1], y[i:i + 1]) for i in range(3)])
    torch.testing.assert_close(batch, single, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("hw", [(32, 32), (16, 48), (40, 24)])
def test_matches_explicit_reference(files, model, hw):
    x, y = _images(b=2, h=hw[0], w=hw[1], seed=3)
    ref = _reference_lpips(files["vgg_state"], files["lin_state"], x, y)
    with torch.no_grad():
        torch.testing.assert_close(model(x, y).double(), ref, rtol=1e-4, atol=1e-7)
        # In float64 the module agrees to rounding: layer taps, scaling, normalization and weights all match.
        got64 = load_lpips(files["vgg.pth"], files["lin.pth"]).double()(x.double(), y.double())
    assert got64.dtype == torch.float64
    torch.testing.assert_close(got64, ref, rtol=1e-10, atol=1e-14)


def test_gradient_reaches_the_inputs_and_parameters_are_frozen(model):
    x, y = _images(seed=4)
    x.requires_grad_(True)
    model(x, y).sum().backward()
    assert torch.isfinite(x.grad).all() and float(x.grad.abs().sum()) > 0
    assert not model.training
    assert not any(p.requires_grad for p in model.parameters())
    assert all(p.grad is None for p in model.parameters())


def test_default_constructor_is_the_unit_weight_baseline():
    m = LPIPS()
    assert not m.training and not any(p.requires_grad for p in m.parameters())
    assert [tuple(w.shape) for w in m.lin] == [(1, c, 1, 1) for c in LIN_CHANNELS]
    assert all(bool((w == 1).all()) for w in m.lin)
    x, y = _images(b=1, h=16, w=16)
    with torch.no_grad():
        assert m(x.double(), y.double()).dtype == torch.float32


# ----------------------------------------------------------------------------- weight files
@pytest.mark.parametrize("vgg_key", ["vgg.pth", "vgg.safetensors"])
@pytest.mark.parametrize("lin_key", ["lin.pth", "lin.safetensors", "flat.pth", "flat.safetensors"])
def test_every_layout_and_format_loads_the_same_weights(files, model, vgg_key, lin_key):
    m = LPIPS.from_files(files[vgg_key], files[lin_key])
    assert not any(p.requires_grad for p in m.parameters()) and not m.training
    for k, w in enumerate(m.lin):
        assert torch.equal(w, files["lin_state"][f"lin{k}.model.1.weight"])
    assert torch.equal(m.vgg.features[28].weight, files["vgg_state"]["features.28.weight"])
    x, y = _images(b=1, seed=5)
    with torch.no_grad():
        torch.testing.assert_close(m(x, y), model(x, y), rtol=0, atol=0)


def _bad_lin(case):
    lin = _lin_state()
    if case == "missing key":
        del lin["lin3.model.1.weight"]
    elif case == "wrong shape":
        lin["lin2.model.1.weight"] = torch.rand(1, 128, 1, 1)
    elif case == "negative":
        lin["lin1.model.1.weight"][0, 5] = -0.1
    elif case == "nan":
        lin["lin4.model.1.weight"][0, 0] = float("nan")
    return lin


@pytest.mark.parametrize("case, which, ext, match", [
    ("missing file", "lin", ".pth", "no such"),
    ("missing file", "vgg", ".pth", "no such"),
    ("garbage", "lin", ".pth", "weights-only"),
    ("garbage", "lin", ".safetensors", "not a valid safetensors"),
    ("garbage", "vgg", ".pth", "weights-only"),
    ("not a state dict", "lin", ".pth", "expected a state dict"),
    ("missing key", "lin", ".pth", "lin3.model.1.weight"),
    ("missing key", "lin", ".safetensors", "lin3.model.1.weight"),
    ("wrong shape", "lin", ".pth",
     r"lin2\.model\.1\.weight.*shape \[1, 128, 1, 1\], expected \[1, 256, 1, 1\]"),
    ("negative", "lin", ".pth", r"lin1\.model\.1\.weight.*negative"),
    ("negative", "lin", ".safetensors", r"lin1\.model\.1\.weight.*negative"),
    ("nan", "lin", ".pth", r"lin4\.model\.1\.weight.*finite"),
    ("missing key", "vgg", ".pth", "features.10.weight"),
    ("wrong shape", "vgg", ".safetensors", r"features\.0\.weight.*shape"),
])
def test_bad_files_give_one_line_errors_naming_the_file(files, tmp_path, case, which, ext, match):
    bad = tmp_path / f"bad_{which}{ext}"
    if case == "garbage":
        bad.write_bytes(b"\x00not a weights file\xff" * 8)
    elif case == "not a state dict":
        torch.save(torch.zeros(3), bad)
    elif case != "missing file" and which == "lin":
        save_state_file(bad, _bad_lin(case))
    elif case == "missing key":
        state = dict(files["vgg_state"])
        del state["features.10.weight"]
        save_state_file(bad, state)
    elif case == "wrong shape":
        save_state_file(bad, {**files["vgg_state"], "features.0.weight": torch.zeros(64, 1, 3, 3)})
    vgg_path, lin_path = (bad, files["lin.pth"]) if which == "vgg" else (files["vgg.pth"], bad)
    with pytest.raises(ToolkitError, match=match) as info:
        load_lpips(vgg_path, lin_path)
    msg = str(info.value)
    assert "\n" not in msg and str(bad) in msg


# ----------------------------------------------------------------------------- inputs
@pytest.mark.parametrize("a, b, match", [
    (torch.rand(3, 32, 32), torch.rand(3, 32, 32), r"\[B, 3, H, W\]"),
    (torch.rand(1, 1, 32, 32), torch.rand(1, 1, 32, 32), r"\[B, 3, H, W\]"),
    (torch.rand(1, 3, 32, 32), torch.rand(2, 3, 32, 32), "one shape"),
    (torch.rand(1, 3, 15, 32), torch.rand(1, 3, 15, 32), "at least 16x16"),
    (torch.zeros(1, 3, 32, 32, dtype=torch.uint8), torch.zeros(1, 3, 32, 32, dtype=torch.uint8), "floating"),
    (torch.full((1, 3, 32, 32), float("nan")), torch.rand(1, 3, 32, 32), "input a contains NaN or inf"),
    (torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 32).index_fill(3, torch.tensor([7]), float("inf")),
     "input b contains NaN or inf"),
])
def test_bad_inputs_raise(model, a, b, match):
    with pytest.raises(ToolkitError, match=match) as info:
        model(a, b)
    assert "\n" not in str(info.value)


def _stress_pair(case):
    x, y = _images(b=2, seed=6)
    if case == "zeros":
        return torch.zeros_like(x), torch.zeros_like(x)
    if case == "ones vs zeros":
        return torch.ones_like(x), torch.zeros_like(x)
    if case == "constant":
        return torch.full_like(x, 0.5), torch.full_like(x, 0.25)
    if case == "tiny 16x16":
        return x[..., :16, :16].contiguous(), y[..., :16, :16].contiguous()
    if case == "outside [0, 1]":
        return x * 2000 - 1000, y * 2000 - 1000
    return x, y.clone()


STRESS_CASES = ["zeros", "ones vs zeros", "constant", "tiny 16x16", "outside [0, 1]", "random"]


@pytest.mark.parametrize("case", STRESS_CASES)
@pytest.mark.parametrize("identical", [False, True])
def test_extreme_inputs_give_finite_distances_and_gradients(model, case, identical):
    a, b = _stress_pair(case)
    a.requires_grad_(True)
    if identical:
        b = a
    else:
        b.requires_grad_(True)
    d = model(a, b)
    assert torch.isfinite(d).all() and bool((d >= 0).all())
    d.sum().backward()
    assert torch.isfinite(a.grad).all()
    if identical:
        assert float(d.detach().abs().max()) == 0 and float(a.grad.abs().max()) == 0
    else:
        assert torch.isfinite(b.grad).all()


def test_all_zero_activations_have_finite_gradients(files):
    """A dead first layer makes every tapped feature vector zero (the 0/0 corner of the normalization):
    the distance is 0 and the gradient finite."""
    m = load_lpips(files["vgg.pth"], files["lin.pth"])
    with torch.no_grad():
        m.vgg.features[0].weight.zero_()
        m.vgg.features[0].bias.fill_(-1.0)  # ReLU(-1) = 0 everywhere downstream of the first layer
        for i in (2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28):
            m.vgg.features[i].bias.zero_()
    x, y = _images(b=1, seed=7)
    x.requires_grad_(True)
    d = m(x, y)
    assert float(d.detach()) == 0
    d.backward()
    assert torch.isfinite(x.grad).all()
