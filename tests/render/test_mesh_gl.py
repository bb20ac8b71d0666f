"""GL mesh rasterizer: a hand-checked cube, a ray-cast reference, textures, context reuse, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import render.gl_context as gl_context
import render.mesh_gl as mesh_gl
from render.mesh_inputs import face_normals
from tests.gl import gl_available
from toolkit.cameras import intrinsics, look_at, project_points
from toolkit.errors import ToolkitError

pytestmark = pytest.mark.skipif(not gl_available(), reason="no headless EGL OpenGL 3.3 context on this machine")


def cube(half: float = 0.5):
    """Unit-ish cube: 8 corners, 12 outward-wound triangles (2 per face, faces in order -z,+z,-x,+x,-y,+y)."""
    v = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)], np.float32)
    idx = lambda x, y, z: 4 * x + 2 * y + z  # noqa: E731
    quads = [  # each quad's corners counter-clockwise seen from outside (right-hand rule -> outward)
        (idx(0, 0, 0), idx(0, 1, 0), idx(1, 1, 0), idx(1, 0, 0)),  # z = -h, normal -z
        (idx(0, 0, 1), idx(1, 0, 1), idx(1, 1, 1), idx(0, 1, 1)),  # z = +h
        (idx(0, 0, 0), idx(0, 0, 1), idx(0, 1, 1), idx(0, 1, 0)),  # x = -h
        (idx(1, 0, 0), idx(1, 1, 0), idx(1, 1, 1), idx(1, 0, 1)),  # x = +h
        (idx(0, 0, 0), idx(1, 0, 0), idx(1, 0, 1), idx(0, 0, 1)),  # y = -h
        (idx(0, 1, 0), idx(0, 1, 1), idx(1, 1, 1), idx(1, 1, 0)),  # y = +h
    ]
    f = []
    for a, b, c, d in quads:
        f += [(a, b, c), (a, c, d)]
    return v, np.array(f, np.int64)


def frontal_camera():
    view = np.eye(4, dtype=np.float32)
    view[2, 3] = 4.0  # cube centre at camera z = 4, front face z = 3.5
    return view, intrinsics(100.0, 100.0, 64.0, 48.0).numpy()


def test_cube_outward_normals_in_fixture():
    v, f = cube()
    n = face_normals(v, f)
    centres = v[f].mean(1)
    assert (np.einsum("ij,ij->i", n, centres) > 0).all()


def test_frontal_cube_hand_checked():
    v, f = cube()
    view, K = frontal_camera()
    out = mesh_gl.render_mesh(v, f, view, K, 128, 96, colors=np.full((8, 3), 0.5, np.float32))
    # Front face corners at (±0.5, ±0.5, 3.5): u = 64 ± 100·0.5/3.5 = 64 ± 14.2857, v = 48 ± 14.2857.
    # Pixel centres j + 0.5 inside (49.714, 78.286) -> columns 50..77; rows 34..61.
    expect = np.zeros((96, 128), bool)
    expect[34:62, 50:78] = True
    np.testing.assert_array_equal(out["mask"], expect)
    uv, _ = project_points(torch.from_numpy(v), torch.from_numpy(view), torch.from_numpy(K))
    front = uv.numpy()[v[:, 2] < 0]
    np.testing.assert_allclose(np.sort(np.unique(front[:, 0].round(4))), [49.7143, 78.2857], atol=1e-3)
    assert out["depth"][expect].min() == pytest.approx(3.5, abs=1e-5)
    assert out["depth"][expect].max() == pytest.approx(3.5, abs=1e-5)
    assert (out["depth"][~expect] == 0).all()
    np.testing.assert_allclose(out["normals"][expect], np.tile([0.0, 0.0, -1.0], (expect.sum(), 1)), atol=1e-6)
    assert set(np.unique(out["tri_id"][expect])) == {0, 1}  # the two triangles of the -z face
    assert (out["tri_id"][~expect] == -1).all()
    # The diagonal a-c splits the square: triangle (a, b, c) with b = (-h, +h) holds the lower-left half.
    assert out["tri_id"][60, 51] == 0 and out["tri_id"][35, 76] == 1
    # Headlight on a face looking at the camera: full albedo; background white.
    np.testing.assert_allclose(out["rgb"][expect], 0.5, atol=1e-6)
    np.testing.assert_allclose(out["rgb"][~expect], 1.0)


def _ray_cast(v, f, view, K, W, H):
    """Reference: per-pixel-centre nearest ray-triangle hit (Möller–Trumbore) in camera space."""
    R, t = view[:3, :3].astype(np.float64), view[:3, 3].astype(np.float64)
    vc = v.astype(np.float64) @ R.T + t
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = np.stack([(jj - K[0, 2]) / K[0, 0], (ii - K[1, 2]) / K[1, 1], np.ones_like(jj)], -1).reshape(-1, 3)
    best_z = np.full(d.shape[0], np.inf)
    best_id = np.full(d.shape[0], -1)
    margin = np.full(d.shape[0], np.inf)  # distance (barycentric) to the nearest edge of the winning hit
    for k, (a, b, c) in enumerate(vc[f]):
        e1, e2 = b - a, c - a
        p = np.cross(d, e2)
        det = p @ e1
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1 / np.where(ok, det, 1), 0)
        s = -a
        u = (p @ s) * inv
        q = np.cross(s, e1)
        w = (d @ q) * inv
        tt = (q @ e2) * inv
        hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (tt > 0)
        z = tt * d[:, 2]
        better = hit & (z < best_z)
        best_z[better], best_id[better] = z[better], k
        margin[better] = np.minimum.reduce([u, w, 1 - u - w])[better]
    return best_z.reshape(H, W), best_id.reshape(H, W), margin.reshape(H, W)


def test_oblique_cube_matches_ray_cast():
    v, f = cube(0.4)
    view = look_at(torch.tensor([1.3, -1.1, -2.2]), torch.tensor([0.05, 0.0, 0.0])).numpy()
    K = intrinsics(90.0, 95.0, 40.5, 30.0).numpy()
    W, H = 80, 64
    out = mesh_gl.render_mesh(v, f, view, K, W, H)
    z_ref, id_ref, margin = _ray_cast(v, f, view, K, W, H)
    mask_ref = id_ref >= 0
    safe = (margin > 1e-3) | ~mask_ref  # ignore pixel centres within float rounding of an edge
    # Outside pixels near the silhouette are ambiguous too: dilate by checking both ways only where safe.
    assert (out["mask"][safe] == mask_ref[safe]).all()
    assert out["mask"].sum() > 500 and abs(int(out["mask"].sum()) - int(mask_ref.sum())) <= 0.02 * mask_ref.sum()
    both = out["mask"] & mask_ref & safe
    np.testing.assert_allclose(out["depth"][both], z_ref[both], rtol=1e-4)
    np.testing.assert_array_equal(out["tri_id"][both], id_ref[both])
    # Normals: the camera-space normal of each hit face; three faces are visible, all facing the camera.
    n_cam = face_normals(v, f) @ view[:3, :3].T
    np.testing.assert_allclose(out["normals"][both], n_cam[id_ref[both]], atol=1e-5)
    assert len(np.unique(id_ref[both] // 2)) == 3
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = np.stack([(jj - K[0, 2]) / K[0, 0], (ii - K[1, 2]) / K[1, 1], np.ones_like(jj)], -1)
    assert (np.einsum("ij,ij->i", out["normals"][both], rays[both]) < 0).all()  # all face the camera


def test_lambert_light_direction_and_ambient():
    v, f = cube()
    view, K = frontal_camera()
    col = np.tile([[0.2, 0.6, 1.0]], (8, 1)).astype(np.float32)
    m = mesh_gl.render_mesh(v, f, view, K, 128, 96, colors=col)["mask"]
    side = mesh_gl.render_mesh(v, f, view, K, 128, 96, colors=col, light_dir=[1, 0, 0], ambient=0.25)
    np.testing.assert_allclose(side["rgb"][m], np.tile(0.25 * col[0], (m.sum(), 1)), atol=1e-6)
    tilted = mesh_gl.render_mesh(v, f, view, K, 128, 96, colors=col, light_dir=[0, -1, -1], ambient=0.0)
    np.testing.assert_allclose(tilted["rgb"][m], np.tile(col[0] / math.sqrt(2), (m.sum(), 1)), atol=1e-5)
    dark = mesh_gl.render_mesh(v, f, view, K, 128, 96, colors=col, background=(0, 0, 0))
    assert (dark["rgb"][~m] == 0).all()


def test_texture_with_uvs():
    # A quad at z = 2 filling the middle of the image, textured with 4 colour quadrants.
    verts = np.array([[-1, -1, 2], [1, -1, 2], [1, 1, 2], [-1, 1, 2]], np.float32)
    faces = np.array([[0, 2, 1], [0, 3, 2]])  # normal -z, towards the camera
    uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    tex = np.zeros((8, 8, 3), np.uint8)
    tex[:4, :4] = (255, 0, 0)
    tex[:4, 4:] = (0, 255, 0)
    tex[4:, :4] = (0, 0, 255)
    tex[4:, 4:] = (255, 255, 0)
    K = intrinsics(32.0, 32.0, 32.0, 32.0).numpy()
    out = mesh_gl.render_mesh(verts, faces, np.eye(4), K, 64, 64, uvs=uvs, texture=tex)
    assert out["mask"][16:48, 16:48].all() and not out["mask"][:15].any()
    np.testing.assert_allclose(out["rgb"][20, 20], [1, 0, 0], atol=1e-6)  # top-left = texture row 0
    np.testing.assert_allclose(out["rgb"][20, 43], [0, 1, 0], atol=1e-6)
    np.testing.assert_allclose(out["rgb"][43, 20], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(out["rgb"][43, 43], [1, 1, 0], atol=1e-6)


def test_one_context_many_sizes_and_torch_inputs():
    ctx = gl_context.create_context()
    v, f = cube()
    view, K = frontal_camera()
    small = mesh_gl.MeshRasterizer(64, 48, ctx=ctx)
    big = mesh_gl.MeshRasterizer(128, 96, ctx=ctx)
    K2 = K.copy()
    K2[:2] *= 0.5
    a = small.render(v, f, view, K2)
    b = big.render(torch.from_numpy(v), torch.from_numpy(f), torch.from_numpy(view), torch.from_numpy(K))
    assert a["mask"].shape == (48, 64) and b["mask"].shape == (96, 128)
    assert a["mask"].sum() == 14 * 14 and b["mask"].sum() == 28 * 28
    small.resize(128, 96)
    c = small.render(v, f, view, K)
    for k in ("mask", "depth", "normals", "tri_id", "rgb"):
        np.testing.assert_array_equal(c[k], b[k])
    big.resize(64, 48)
    np.testing.assert_array_equal(big.render(v, f, view, K2)["mask"], a["mask"])
    small.release()
    big.release()
    ctx.release()


def test_smooth_normals_on_sphere_are_unit_and_radial():
    # An octahedron subdivided twice and pushed to the unit sphere: smooth normals ~ radial.
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    view = np.eye(4, dtype=np.float32)
    view[2, 3] = 4.0
    K = intrinsics(60.0, 60.0, 32.0, 32.0).numpy()
    out = mesh_gl.render_mesh(s.vertices, s.faces, view, K, 64, 64, smooth=True)
    m = out["mask"]
    n = out["normals"][m]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    jj, ii = np.meshgrid(np.arange(64) + 0.5, np.arange(64) + 0.5)
    d = np.stack([(jj - 32) / 60, (ii - 32) / 60, np.ones_like(jj)], -1)[m]
    p = d * out["depth"][m][:, None] - [0, 0, 4]
    radial = p / np.linalg.norm(p, axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", n, radial).min() > 0.99


def test_stress_degenerate_and_extreme():
    view, K = frontal_camera()
    # Zero-area triangles, a vertex behind the camera, huge coordinates: finite outputs, no crash.
    v = np.array([[0, 0, 1], [0, 0, 1], [0, 0, 1], [-1, -1, -5], [1, -1, 3], [0, 1, 3], [1e6, 1e6, 50],
                  [-1e6, 1e6, 50], [0, -1e6, 50]], np.float32)
    f = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    out = mesh_gl.render_mesh(v, f, view, K, 32, 24)
    for k in ("rgb", "depth", "normals"):
        assert np.isfinite(out[k]).all(), k
    assert out["mask"].any()
    assert (out["depth"][out["mask"]] > 0.01).all()
    assert set(np.unique(out["tri_id"])) <= {-1, 1, 2}


@pytest.mark.parametrize(
    "verts,faces,match",
    [
        (np.array([[0, 0, 1], [1, 0, 1], [np.nan, 1, 1]]), np.array([[0, 1, 2]]), "verts: contains NaN"),
        (np.zeros((3, 3)), np.array([[0, 1, 3]]), r"faces: indices must be in \[0, 2\]"),
        (np.zeros((3, 3)), np.array([[0, -1, 2]]), r"faces: indices must be in"),
        (np.zeros((3, 3)), np.array([[0.0, 1.0, 2.0]]), "faces: expected integer"),
        (np.zeros((0, 3)), np.zeros((0, 3), np.int64), "mesh is empty"),
        (np.zeros((3, 3)), np.zeros((0, 3), np.int64), "mesh is empty"),
        (np.zeros((3, 2)), np.array([[0, 1, 2]]), r"verts: expected shape \[N, 3\]"),
        (np.zeros((3, 3)), np.array([0, 1, 2]), r"faces: expected shape \[N, 3\]"),
    ],
)
def test_bad_mesh_inputs(verts, faces, match):
    view, K = frontal_camera()
    with pytest.raises(ToolkitError, match=match):
        mesh_gl.render_mesh(verts, faces, view, K, 16, 16)


def test_bad_other_inputs():
    v, f = cube()
    view, K = frontal_camera()
    r = mesh_gl.MeshRasterizer(16, 16)
    with pytest.raises(ToolkitError, match="colors"):
        r.render(v, f, view, K, colors=np.zeros((7, 3)))
    with pytest.raises(ToolkitError, match="texture given without uvs"):
        r.render(v, f, view, K, texture=np.zeros((2, 2, 3)))
    with pytest.raises(ToolkitError, match="viewmat"):
        r.render(v, f, view[:3], K)
    with pytest.raises(ToolkitError, match="K: contains NaN"):
        r.render(v, f, view, np.full((3, 3), np.nan))
    with pytest.raises(ToolkitError, match="near/far"):
        r.render(v, f, view, K, near=0.0)
    with pytest.raises(ToolkitError, match="light_dir"):
        r.render(v, f, view, K, light_dir=[0, 0, 0])
    with pytest.raises(ToolkitError, match="width and height"):
        mesh_gl.MeshRasterizer(0, 16)
    r.release()


def test_missing_egl_names_the_library(monkeypatch):
    import moderngl

    def fail(*a, **k):
        raise Exception("libEGL.so.1: cannot open shared object file")

    monkeypatch.setattr(moderngl, "create_context", fail)
    with pytest.raises(ToolkitError, match="EGL.*libEGL"):
        gl_context.create_context()


def test_render_views_equals_single_renders():
    v, f = cube(0.4)
    r = mesh_gl.MeshRasterizer(48, 40)
    K = intrinsics(60.0, 60.0, 24.0, 20.0).numpy()
    eyes = [torch.tensor(e) for e in ([1.5, -0.5, -2.0], [-1.0, 0.8, -2.5], [0.0, 0.0, -3.0])]
    views = np.stack([look_at(e, torch.zeros(3)).numpy() for e in eyes])
    lights = np.array([[0, 0, -1], [1, 0, -1], [0, 1, -1]], np.float32)
    cols = np.random.default_rng(0).random((8, 3)).astype(np.float32)
    many = r.render_views(v, f, views, np.stack([K] * 3), light_dir=lights, colors=cols)
    for c in range(3):
        one = r.render(v, f, views[c], K, light_dir=lights[c], colors=cols)
        np.testing.assert_array_equal(one["tri_id"], many[c]["tri_id"])
        np.testing.assert_array_equal(one["rgb"], many[c]["rgb"])
        np.testing.assert_array_equal(one["depth"], many[c]["depth"])
    with pytest.raises(ToolkitError, match="light_dir"):
        r.render_views(v, f, views, np.stack([K] * 3), light_dir=np.ones((2, 3)))
    with pytest.raises(ToolkitError, match="Ks"):
        r.render_views(v, f, views, np.stack([K] * 2))
    r.release()


def _render_in_child() -> str:
    v, f = cube()
    view, K = frontal_camera()
    try:
        mesh_gl.render_mesh(v, f, view, K, 16, 16)
    except ToolkitError as e:
        return str(e)
    return "rendered"


def test_forked_child_gets_a_clear_error_not_a_hang():
    import multiprocessing as mp

    gl_context.shared_context()  # the parent holds a context before forking, as a DataLoader parent would
    with mp.get_context("fork").Pool(1) as pool:
        msg = pool.apply_async(_render_in_child).get(timeout=60)
    assert "forked after OpenGL was initialised" in msg and "spawn" in msg


def test_renders_survive_another_current_context():
    """Two standalone contexts in one process (the mesh rasterizer's and, e.g., the preview's): whichever
    was made current last must not receive the rasterizer's GL calls (when it does, the data CLI's contact
    sheet comes out blank after the preview tests have run)."""
    v, f = cube()
    view, K = frontal_camera()
    ras = mesh_gl.MeshRasterizer(64, 48)
    before = ras.render(v, f, view, K)
    other = gl_context.create_context()  # made current on creation
    tex = other.texture((16, 16), 4)  # objects in the other context must not clash with ours
    late = mesh_gl.MeshRasterizer(80, 60)  # created while the other context is current
    again = ras.render(v, f, view, K)
    for k in ("mask", "depth", "tri_id", "rgb"):
        np.testing.assert_array_equal(again[k], before[k])
    assert late.render(v, f, view, K)["mask"].sum() > 0
    tex.release()
    other.release()
    late.release()
    np.testing.assert_array_equal(ras.render(v, f, view, K)["mask"], before["mask"])
    ras.release()


def _square(x0: float):
    """A flat square in the plane z = 3 whose left edge sits at camera x = x0 (right edge far off-image)."""
    v = np.array([[x0, -5, 3], [5, -5, 3], [5, 5, 3], [x0, 5, 3]], np.float32)
    return v, np.array([[0, 1, 2], [0, 2, 3]], np.int64)


def test_supersample_keeps_discrete_buffers_and_antialiases_edges():
    v, f = cube(0.4)
    r = mesh_gl.MeshRasterizer(48, 40)
    K = intrinsics(60.0, 60.0, 24.0, 20.0).numpy()
    view = look_at(torch.tensor([1.5, -0.5, -2.0]), torch.zeros(3)).numpy()
    one = r.render(v, f, view, K, ambient=0.5)
    ss = r.render(v, f, view, K, ambient=0.5, supersample=3)
    for key in ("mask", "tri_id", "depth", "normals"):  # exactly the s = 1 samples
        np.testing.assert_array_equal(one[key], ss[key])
    assert ss["rgb"].shape == one["rgb"].shape and ss["rgb"].dtype == np.float32
    # Pixels whose 3 x 3 neighbourhood is all background or all one face are unchanged; silhouette pixels blend.
    from scipy import ndimage

    ids = one["tri_id"]
    flat = (ndimage.minimum_filter(ids, 3) == ndimage.maximum_filter(ids, 3))
    np.testing.assert_allclose(ss["rgb"][flat & ~one["mask"]], 1.0)
    edge = one["mask"] ^ ndimage.binary_erosion(one["mask"])
    assert np.abs(ss["rgb"][edge] - one["rgb"][edge]).max() > 0.05
    r.release()


def test_supersample_coverage_follows_a_subpixel_edge():
    """A black square's edge moved by a third of a pixel changes the edge pixel by a third of the contrast."""
    r = mesh_gl.MeshRasterizer(16, 8)
    K = intrinsics(30.0, 30.0, 8.0, 4.0).numpy()  # 1 px = 0.1 world units at z = 3
    col = np.zeros((4, 3), np.float32)
    vals = []
    for shift in (0.0, 1 / 3, 2 / 3):
        x0 = (8.0 + shift - 8.0) / 10.0  # left edge at pixel x = 8 + shift
        out = r.render(*_square(x0), np.eye(4, dtype=np.float32), K, colors=col, ambient=1.0, supersample=3)
        vals.append(float(out["rgb"][4, 8, 0]))  # pixel column 8 spans x in [8, 9)
    # Covered fraction of column 8 is 1, 2/3, 1/3 -> white fraction 0, 1/3, 2/3.
    np.testing.assert_allclose(vals, [0.0, 1 / 3, 2 / 3], atol=1e-5)
    r.release()


@pytest.mark.parametrize("bad", [0, 2, -1, 1.5, True])
def test_supersample_must_be_odd_positive_int(bad):
    v, f = cube()
    r = mesh_gl.MeshRasterizer(16, 16)
    view, K = frontal_camera()
    with pytest.raises(ToolkitError, match="supersample"):
        r.render(v, f, view, K, supersample=bad)
    r.release()


def test_supersample_beyond_the_gl_texture_limit_is_a_clear_error(monkeypatch):
    v, f = cube()
    r = mesh_gl.MeshRasterizer(64, 48)
    view, K = frontal_camera()
    monkeypatch.setitem(r.ctx.info, "GL_MAX_TEXTURE_SIZE", 128)  # moderngl caches info as a dict
    with pytest.raises(ToolkitError, match="supersample.*192x144.*limit of 128"):
        r.render(v, f, view, K, supersample=3)
    r.release()
