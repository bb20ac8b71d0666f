"""Input of ``apps.redirect`` from a folder of normalized face crops with a labels CSV: the rows that
``apps.labels_table`` reads and validates, as dataset-like items (see docs/redirect.md).

Frames: the head-to-camera rotation is rebuilt from (pitch, yaw, roll) with the normalization's no-roll
rule (the head x axis has no camera-y component), so the synthetic dataset's own rows round-trip exactly;
the camera looks along +z at the face centre (the mean of iBUG landmarks 36, 39, 42, 45, 48, 54 of the
run's geometry) from ``distance`` metres, principal point at the image centre. The world frame is the
head frame (``pose`` = 0, the centre of the training poses) and ``w2c`` carries the whole transform.
"""

from __future__ import annotations

import numpy as np
import torch

from apps.labels_table import LabelRow, labels_csv_file, read_labels
from toolkit.errors import ToolkitError
from toolkit.images import read_image
from toolkit.rotations import pitchyaw_to_vector, so3_exp

FACE_CENTER_LANDMARKS = [36, 39, 42, 45, 48, 54]


def head_rotation(pitch_yaw_roll: torch.Tensor) -> torch.Tensor:
    """[B, 3] (pitch, yaw, roll) radians -> [B, 3, 3] head-to-camera rotation.

    ``toolkit.rotations.normalized_head_rotation`` of (pitch, yaw) (the normalization's no-roll rule: the head
    x axis has no camera-y component), then ``roll`` about the head's own z axis (the face direction).
    """
    from toolkit.rotations import normalized_head_rotation

    roll = torch.zeros_like(pitch_yaw_roll)
    roll[:, 2] = pitch_yaw_roll[:, 2]
    return normalized_head_rotation(pitch_yaw_roll[:, :2]) @ so3_exp(roll)


def visible_eyes(face_alpha: torch.Tensor, eyes_alpha: torch.Tensor) -> torch.Tensor:
    """[..., H, W] splatted alphas -> [..., H, W] float mask of the visible eyeball: covered by the eye
    Gaussians where the face layer (lids, socket) is open."""
    return ((eyes_alpha > 0.5) & (face_alpha < 0.5)).float()


class LabelsCsvSource:
    """Rows of a labels CSV as dataset-like items for the redirect app (see the module docstring)."""

    def __init__(self, csv_path, res: int, landmarks_head: torch.Tensor, mesh_head: torch.Tensor, *,
                 focal: float | None = None, distance: float | None = None, default_distance: float = 0.6,
                 default_crop: float = 0.26, code_widths: tuple[int, int] = (80, 64)):
        self.rows, self.size = read_labels(csv_path, focal=focal, distance=distance, default_distance=default_distance,
                                           default_crop=default_crop, code_widths=code_widths)
        self.path = labels_csv_file(csv_path)  # the folder and its labels.csv are the same input
        self.res = int(res)
        self.landmarks_head = landmarks_head.float()  # [68, 3], the run's geometry (head frame)
        self.mesh_head = mesh_head.float()  # [V, 3]
        self.face_center = self.landmarks_head[FACE_CENTER_LANDMARKS].mean(0)

    def __len__(self) -> int:
        return len(self.rows)

    def stamp(self) -> str:
        """A hash of what the rows' contents depend on: the CSV's text, each image's and mask's path, size and
        modification time, and the codes (a resumed redirect compares it, ``apps.redirect_parts.input_stamp``)."""
        import hashlib

        from toolkit.io import file_stamp

        h = hashlib.sha1(self.path.read_bytes())
        for r in self.rows:
            h.update(";".join(file_stamp(q) for q in (r.image, r.mask) if q is not None).encode())
            if r.code is not None:
                h.update(r.code.tobytes())
        return h.hexdigest()

    def _image(self, r: LabelRow) -> torch.Tensor:
        from train.data.dataset import resize_image

        bgr = read_image(r.image, f"{self.path} line {r.line}, column 'image':")
        rgb = resize_image(bgr[..., ::-1].astype(np.float32) / 255.0, self.res)
        return torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))

    def _mask(self, r: LabelRow) -> torch.Tensor | None:
        from train.data.dataset import resize_image

        if r.mask is None:
            return None
        m = (read_image(r.mask, f"{self.path} line {r.line}, column 'mask':", gray=True) > 0).astype(np.float32)
        return torch.from_numpy((resize_image(m, self.res) > 0.5).astype(np.float32))[None]

    def geometry(self, idx: list[int]) -> dict[str, torch.Tensor]:
        """Camera, pose and labels of rows ``idx`` (no model needed)."""
        rows = [self.rows[i] for i in idx]
        pyr = torch.tensor([r.head for r in rows], dtype=torch.float32)
        R = head_rotation(pyr)
        d = torch.tensor([r.distance for r in rows], dtype=torch.float32)
        t = torch.stack([torch.zeros_like(d), torch.zeros_like(d), d], -1) - R @ self.face_center
        # World = head frame (pose 0, the centre of the poses the model was trained on); the camera carries
        # the whole head-to-camera transform. The model's pose inputs are not invariant to how that transform
        # is split between pose and camera; camera-frame head poses (often > 45°) lie outside the rig-world
        # poses of training (yaw ±25°, pitch ±15°). See docs/redirect.md for the measured effect.
        pose = torch.zeros(len(rows), 6)
        V = torch.eye(4).repeat(len(rows), 1, 1)
        V[:, :3, :3], V[:, :3, 3] = R, t
        s = self.res / self.size
        K = torch.zeros(len(rows), 3, 3)
        K[:, 0, 0] = K[:, 1, 1] = torch.tensor([r.focal for r in rows]) * s
        K[:, 0, 2] = K[:, 1, 2] = self.res / 2
        K[:, 2, 2] = 1
        gaze_cam = torch.tensor([r.gaze if r.gaze is not None else (0.0, 0.0) for r in rows], dtype=torch.float32)
        # The image's gaze in the head frame: g_head = Rᵀ g_cam.
        from toolkit.rotations import vector_to_pitchyaw

        gaze_head = vector_to_pitchyaw(torch.einsum("bji,bj->bi", R, pitchyaw_to_vector(gaze_cam)))
        return {"pose": pose, "R": R, "t": t, "K": K, "viewmat": V, "face_head_pose": pyr[:, :2],
                "gaze_head": gaze_head}

    def items(self, idx: list[int], model, renderer, device, *, fit_steps: int, fit_lr: float = 1e-2) -> list[dict]:
        """Dataset-like dicts (the keys ``apps.redirect.render_chunk`` reads) for rows ``idx``.

        Rows without a code get one by test-time fitting on their image (``fit_steps`` steps from the zero
        code, the mean of the synthetic codes); rows without a mask use the model's splatted silhouette.
        """
        from train.evaluation.fitting import face_only_mask, test_time_fit

        geo = {k: v.to(device) for k, v in self.geometry(idx).items()}
        rows = [self.rows[i] for i in idx]
        res = self.res
        code = torch.stack([torch.from_numpy(r.code) if r.code is not None else torch.zeros(model.config.code_dim) for r in rows]).to(device)

        def silhouettes(c):
            with torch.no_grad():
                maps = model(c, geo["pose"], geo["gaze_head"], geo["viewmat"], geo["K"], res, res,
                             renders=("head", "face", "eyes"))
            up = lambda a: torch.nn.functional.interpolate(a, size=(res, res), mode="bilinear",  # noqa: E731
                                                           align_corners=False)
            return up(maps["head_alpha"]), up(maps["face_alpha"]), up(maps["eyes_alpha"])

        user_masks = [self._mask(r) for r in rows]
        images = [self._image(r) for r in rows]
        fit = [i for i, r in enumerate(rows) if r.code is None]
        if fit and fit_steps > 0:
            head_a, face_a, eyes_a = silhouettes(code)
            head = torch.stack([m.to(device) if m is not None else (head_a[i] > 0.5).float()
                                for i, m in enumerate(user_masks)])
            # Compare the face only, as the evaluation does: the image's eyes show its own gaze, which the
            # code must not learn (the redirected rows would copy it).
            mask = face_only_mask(head, visible_eyes(face_a, eyes_a))
            image = torch.stack(images).to(device)
            sel = torch.tensor(fit, device=device)
            batch = {"code": code[sel], "in_pose": geo["pose"][sel], "in_gaze_head": geo["gaze_head"][sel],
                     "in_viewmat": geo["viewmat"][sel], "K": geo["K"][sel]}
            with torch.enable_grad():
                code[sel] = test_time_fit(model, renderer, batch, image[sel], mask[sel], res, fit_steps, lr=fit_lr)
            bad = [rows[i].line for i in fit if not torch.isfinite(code[i]).all()]
            if bad:
                raise ToolkitError(f"{self.path} line {bad[0]}: the fit of the row's code diverged (non-finite); "
                                   "try a lower --fit-lr or fewer --fit-steps")
        head_a, face_a, eyes_a = silhouettes(code)
        R, t = geo["R"].cpu(), geo["t"].cpu()
        out = []
        for i in range(len(rows)):
            head = user_masks[i] if user_masks[i] is not None else (head_a[i].cpu() > 0.5).float()
            eyes = visible_eyes(face_a[i], eyes_a[i]).cpu()[0]
            uvw = (self.landmarks_head @ R[i].T + t[i]) @ geo["K"][i].cpu().T
            uv = uvw[:, :2] / uvw[:, 2:].clamp_min(1e-6)
            # Split the eye pixels by the nearer projected eye (iBUG 36-41 = image-left eye, 42-47 = right).
            jj, ii = torch.meshgrid(torch.arange(res) + 0.5, torch.arange(res) + 0.5, indexing="xy")
            dl = (jj - uv[36:42, 0].mean()) ** 2 + (ii - uv[36:42, 1].mean()) ** 2
            dr = (jj - uv[42:48, 0].mean()) ** 2 + (ii - uv[42:48, 1].mean()) ** 2
            left = eyes * (dl <= dr)
            out.append({
                "latent_code": code[i].detach().cpu(), "pose": geo["pose"][i].cpu(), "viewmat": geo["viewmat"][i].cpu(),
                "K": geo["K"][i].cpu(), "head_mask": head, "left_eye_mask": left[None], "right_eye_mask": (eyes - left)[None],
                "face_head_pose": geo["face_head_pose"][i].cpu(), "cam_index": torch.tensor(0),
                "frame_index": torch.tensor(idx[i]), "landmarks": uv, "image": images[i],
                "pitchyaw_head": geo["gaze_head"][i].cpu(),  # the image's own gaze (0, 0 when the row has none)
                "landmarks_3d": self.landmarks_head, "scale": torch.ones(1), "vertice": self.mesh_head,
            })
        return out
