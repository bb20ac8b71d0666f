"""The protocol's redirection pairs: which of a subject's pairs are evaluated, their tensors, and their renders.

A pair is an input row and a target row of one held-out subject (``train.data.pairing``). The model renders
with the **target's** camera, head pose and head-frame gaze and the input's shape code; the target is the
ground truth. Under the synthetic protocol the target is the input's view re-rendered by the generator at the
target row's gaze (so the target's camera and head pose are the input's); under the stored protocol (real
files) it is the target row as stored, with its own camera and head pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from toolkit.errors import ToolkitError


def spread_indices(total: int, n: int) -> list[int]:
    """``n`` (<= ``total``) indices spread evenly over ``range(total)``: the first and (for ``n`` >= 2) the last.

    The evaluation takes its pairs this way rather than the first ``n``: a subject's pairs run through its input
    rows in order (frame by frame, 18 cameras each), so the first ``n`` would all share one input frame."""
    if not 0 <= n <= total:
        raise ToolkitError(f"spread_indices: expected 0 <= n <= total, got n={n}, total={total}")
    if n == 1:
        return [0]
    return [round(i * (total - 1) / (n - 1)) for i in range(n)]


@dataclass
class SubjectPairs:
    """One test subject's evaluated pairs (P of them), on the evaluation's device.

    ``input`` and ``target`` are the images [P, 3, H, W], ``input_mask`` and ``target_mask`` their head masks
    [P, 1, H, W]; ``indices`` each pair's index in the subject's pairing and ``items`` the pairs as
    :func:`train.data.pairing.redirection_pairs` gives them; ``protocol`` its ``"synthetic"`` (generator
    targets at the input's view) or ``"stored"`` (the stored target rows, each at its own view)."""

    name: str
    indices: list[int]
    items: list[dict[str, Any]]
    device: Any
    input: torch.Tensor
    target: torch.Tensor
    input_mask: torch.Tensor
    target_mask: torch.Tensor
    protocol: str = "synthetic"

    def inputs(self, key: str) -> torch.Tensor:
        """The input rows' ``key`` stacked [P, ...], float, on the device."""
        return torch.stack([torch.as_tensor(it["input"][key]) for it in self.items]).float().to(self.device)

    def at_target_view(self, key: str) -> torch.Tensor:
        """``key`` [P, ...] of the view the pairs are rendered and scored at (camera ``viewmat``/``K``, head
        ``pose``/``face_head_pose``, ``landmarks``): the stored target rows', else the inputs' (a synthetic
        target is the input's view)."""
        if self.protocol != "stored":
            return self.inputs(key)
        return torch.stack([torch.as_tensor(it["target"][key]) for it in self.items]).float().to(self.device)

    def render_batch(self) -> dict[str, torch.Tensor]:
        """What :func:`render_pairs` and test-time fitting read: the input's code, the target's view and
        head-frame gaze, and (``in_*``) the input's own view (``in_K`` its intrinsics: a real subject's cameras
        differ), gaze and head mask, with the input's landmarks."""
        st, tv = self.inputs, self.at_target_view
        target_gaze = torch.stack([torch.as_tensor(it["target"]["pitchyaw_head"]) for it in self.items])
        return {"code": st("latent_code"), "pose": tv("pose"), "viewmat": tv("viewmat"), "K": tv("K"),
                "gaze_head": target_gaze.float().to(self.device),
                "in_gaze_head": st("pitchyaw_head"), "in_pose": st("pose"), "in_viewmat": st("viewmat"),
                "in_K": st("K"), "landmarks": st("landmarks"), "in_head_mask": self.input_mask}

    def target_labels(self) -> torch.Tensor | None:
        """[P, 4] the targets' camera-frame labels (gaze pitch/yaw, head pitch/yaw) as the estimators are
        trained on them, or None when a target has no ``pitchyaw_cam`` (``GazeDataset`` rows always carry one:
        the file's, or derived from the head-frame gaze when the file has none; other target sources may not).
        The head-pose label is that of the target's view (:meth:`at_target_view`: a synthetic target shares its
        input's view and head pose)."""
        if not all("pitchyaw_cam" in it["target"] for it in self.items):
            return None
        gaze = torch.stack([torch.as_tensor(it["target"]["pitchyaw_cam"]).float() for it in self.items])
        return torch.cat([gaze.to(self.device), self.at_target_view("face_head_pose")], 1)


def load_subject_pairs(subject_file: Path, pairing_rows: np.ndarray | None, *, res: int, seed: int,
                       pairs_per_subject: int, device, layout: str = "auto") -> SubjectPairs:
    """``pairs_per_subject`` pairs of one subject file, spread over its pairing (:func:`spread_indices`).

    ``pairing_rows`` [P, 2] (input row, target row) from a pairing file, or None: pairs generated with
    ``seed`` (``train.data.pairing.synthetic_pairs``). The file's protocol (generator or stored targets)
    follows from the file (``train.data.pairing.redirection_pairs``), read in ``layout``."""
    from train.data.pairing import redirection_pairs

    pairs = redirection_pairs(subject_file, pairing_rows, res=res, seed=seed, layout=layout)
    indices = spread_indices(len(pairs), min(pairs_per_subject, len(pairs)))
    items = [pairs[i] for i in indices]
    stack = lambda row, key: torch.stack([it[row][key] for it in items]).to(device)  # noqa: E731
    return SubjectPairs(name=Path(subject_file).name, indices=indices, items=items, device=device,
                        target=stack("target", "image"), input=stack("input", "image"),
                        target_mask=stack("target", "head_mask"), input_mask=stack("input", "head_mask"),
                        protocol=pairs.protocol)


def own_gaze_batch(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The pairs' render batch turned back on their inputs: the input's head pose, camera (``in_K`` where the
    batch has it) and head-frame gaze, the same code. Rendering it asks the model to reproduce the input, with
    no redirection."""
    return {**batch, "pose": batch["in_pose"], "viewmat": batch["in_viewmat"], "gaze_head": batch["in_gaze_head"],
            "K": batch.get("in_K", batch["K"])}


@torch.no_grad()
def render_pairs(model, renderer, batch: dict[str, torch.Tensor], res: int, steps: int) -> torch.Tensor:
    """[B, 3, res, res] renders of a :meth:`SubjectPairs.render_batch` (``steps``: a diffusion renderer's
    sampling steps)."""
    maps = model(batch["code"], batch["pose"], batch["gaze_head"], batch["viewmat"], batch["K"], res, res,
                 renders=("head",))
    if hasattr(renderer, "diffusion"):
        return renderer.render(maps["head"], batch["code"], gaze=batch["gaze_head"], pose=batch["pose"], steps=steps)
    return renderer.render(maps["head"], batch["code"], gaze=batch["gaze_head"], pose=batch["pose"])
