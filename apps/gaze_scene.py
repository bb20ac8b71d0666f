"""A Gaussian scene prepared for live gaze changes (the preview's window and sweep), and the cameras that
frame it."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from toolkit.errors import ToolkitError


def frame_camera(scene, width: int, height: int, fov_y_deg: float = 25.0, fill: float = 0.95):
    """A frontal camera (the face looks towards -z) whose view the scene's bulk fills."""
    from toolkit.cameras import Camera, intrinsics_from_fov, look_at

    m = scene.means.detach().cpu().double()
    if m.shape[0] == 0:
        raise ToolkitError("scene has no Gaussians: nothing to preview")
    lo, hi = torch.quantile(m, 0.005, 0), torch.quantile(m, 0.995, 0)
    centre, half = (lo + hi) / 2, ((hi - lo) / 2).clamp_min(1e-6)
    K = intrinsics_from_fov(fov_y_deg, width, height)
    tan_y = math.tan(math.radians(fov_y_deg) / 2)
    tan_x = tan_y * width / height
    dist = float(max(half[0] / tan_x, half[1] / tan_y) / fill + half[2])
    eye = centre + torch.tensor([0.0, 0.0, -dist], dtype=torch.float64)
    return Camera(K, look_at(eye.float(), centre.float()), width, height)


def orbit_camera(base, target, yaw: float, pitch: float):
    """``base`` camera moved on a sphere about ``target`` [3] by ``yaw`` (about the vertical) and ``pitch``
    (positive = from above) radians, still looking at ``target`` with the head's up (-y) up."""
    from toolkit.cameras import Camera, look_at

    target = torch.as_tensor(target, dtype=torch.float64)
    d = base.center.double() - target
    pitch = max(-1.4, min(1.4, pitch))  # stay clear of the poles, where look_at has no up direction
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    Ry = torch.tensor([[cy, 0, -sy], [0, 1, 0], [sy, 0, cy]], dtype=torch.float64)
    Rx = torch.tensor([[1, 0, 0], [0, cp, sp], [0, -sp, cp]], dtype=torch.float64)
    eye = target + Ry @ Rx @ d
    return Camera(base.K, look_at(eye.float(), target.float()), base.width, base.height)


@dataclass
class GazeScene:
    """A scene prepared for live gaze changes: activated numpy arrays, display colours, the eye set and
    each eye's rotation sphere. A gaze frame rotates only the eye rows (rigidly about each eyeball's
    centre, as ``toolkit.eyes.redirect_eyes`` does) and hands the splatter arrays that differ there only.
    ``no_scrub`` says why gaze scrubbing is disabled ("" when it is not)."""

    scene: object
    colors: np.ndarray
    dynamic: np.ndarray | None
    spheres: list | None
    eye_info: dict = field(default_factory=dict)
    arrays: tuple = ()
    eye_index: dict = field(default_factory=dict)
    no_scrub: str = ""

    @classmethod
    def prepare(cls, scene) -> "GazeScene":
        from render.cull import finite_scales
        from render.preview_scene import FeatureColors, eye_dynamics
        from toolkit.eyes import EYE_PARTS, eyeball_info

        scene.validate()
        colors = FeatureColors(scene.features)(scene.features)
        part = scene.part.cpu().numpy()
        no_scrub = "" if np.isin(part, list(EYE_PARTS.values())).any() else NO_EYES
        try:
            info = eyeball_info(scene)
        except ToolkitError as e:
            # The eye Gaussians are there but give no eyeball (no metadata["eyes"] entry and too few or
            # coplanar means for a sphere; malformed metadata already failed validate): say that, not "no eyes".
            info = {}
            no_scrub = no_scrub or f"the scene's eye Gaussians cannot be turned ({e}): gaze scrubbing is disabled"
        dynamic, spheres = eye_dynamics(scene) if info else (None, None)
        # finite_scales: a log-scale that overflows float32 is culled as huge (render.cull), not refused as inf.
        arrays = tuple(t.detach().cpu().float().numpy().copy() for t in
                       (scene.means, scene.quats, finite_scales(scene.scales.float()), scene.opacities))
        index = {name: np.flatnonzero(part == EYE_PARTS[name]) for name in info}
        return cls(scene, colors, dynamic, spheres, info, arrays, index, no_scrub if not info else "")

    @property
    def can_scrub(self) -> bool:
        return bool(self.eye_info)

    def arrays_at(self, pitch: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        """(means [N, 3], quats [N, 4]) with both eyes turned to head-frame gaze (pitch, yaw) radians."""
        from render.preview_footprints import affine_rows
        from toolkit.eyes import gaze_rotation
        from toolkit.rotations import matrix_to_quat

        means, quats = self.arrays[0], self.arrays[1]
        if not self.can_scrub:
            return means, quats
        means, quats = means.copy(), quats.copy()
        R = gaze_rotation(torch.tensor([pitch, yaw], dtype=torch.float32))
        # toolkit.eyes.rotate_about in numpy (elementwise; no threaded kernels for a few thousand rows).
        aw, ax, ay, az = matrix_to_quat(R).numpy().astype(np.float32)
        R = R.numpy().astype(np.float32)
        for name, eye in self.eye_info.items():
            idx = self.eye_index[name]
            c = eye["center"].detach().cpu().numpy().astype(np.float32)
            means[idx] = affine_rows(means[idx] - c, R, c)
            b = quats[idx]
            b[(b == 0).all(1)] = (1, 0, 0, 0)  # an all-zero quaternion is the identity, and turns like one
            bw, bx, by, bz = b.T
            quats[idx] = np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                                   aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], 1)
        return means, quats

    def scene_at(self, pitch: float, yaw: float):
        """The scene itself with the eyes turned (``toolkit.eyes.redirect_eyes``), e.g. for the torch splatter."""
        from toolkit.eyes import redirect_eyes

        return redirect_eyes(self.scene, (pitch, yaw), info=self.eye_info) if self.can_scrub else self.scene

    def draw(self, splatter, camera, pitch: float = 0.0, yaw: float = 0.0, *, fresh: bool = False):
        """Draw the scene at this gaze. Only the eye rows are compared with the splatter's last inputs, unless
        ``fresh``: the splatter may last have drawn something else (a splatter the caller passed in)."""
        means, quats = self.arrays_at(pitch, yaw)
        return splatter.draw(means, quats, self.arrays[2], self.arrays[3], self.colors, camera.viewmat,
                             camera.K, dynamic=self.dynamic, dynamic_spheres=self.spheres,
                             may_change=None if fresh else self.eye_ids)

    @property
    def eye_ids(self) -> np.ndarray:
        """Rows a gaze change can touch (all other arrays are passed unchanged, frame after frame)."""
        return np.concatenate([*self.eye_index.values(), np.zeros(0, np.int64)])


NO_EYES = "scene has no eye Gaussians (part 1 or 2): gaze scrubbing is disabled"


def visibility_warning(camera, splatter) -> str | None:
    """After a full frame through ``camera`` (``splatter.stats`` of that frame): why Gaussians are
    not drawn, by the shared cull rule's tests (``render.cull``), or why nothing is; None when all are drawn."""
    from render.cull import REASONS

    st = splatter.stats
    n, culled, drawn = st.get("n", 0), st.get("culled", 0), st.get("drawn")
    if not culled and drawn != 0:
        return None
    why = ""
    if culled:
        counts = splatter.culled_by_test(camera.viewmat, camera.K)
        why = "; ".join(f"{k} with {REASONS[name]}" for name, k in counts.items())
    if drawn == 0:
        faint = n - culled
        parts = [f"{culled} culled ({why})" if culled else "", f"{faint} with opacity below 1/255" if faint else ""]
        return (f"nothing is drawn from this view: of {n} Gaussians, {' and '.join(p for p in parts if p)}; "
                "the frames show only the background")
    return f"{culled} of {n} Gaussians are not drawn ({why})"
