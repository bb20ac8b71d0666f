"""Inputs of the redirection pairs as test-time fitting takes them, and the fit's error on them."""

import torch


def pair_inputs(subject_file, n: int):
    """(batch, image, head mask, eye mask) of the inputs of the first ``n`` pairs, at 64²."""
    from train.data.pairing import SyntheticRedirectionPairs

    pairs = SyntheticRedirectionPairs(subject_file, res=64, seed=0)
    items = [pairs[i]["input"] for i in range(n)]
    st = lambda k: torch.stack([torch.as_tensor(it[k]) for it in items]).float()  # noqa: E731
    batch = {"code": st("latent_code"), "in_pose": st("pose"), "in_viewmat": st("viewmat"), "K": st("K"),
             "in_gaze_head": st("pitchyaw_head")}
    return batch, st("image"), st("head_mask"), (st("left_eye_mask") + st("right_eye_mask")).clamp(0, 1)


def render_input_error(model, renderer, batch, image, mask, code) -> float:
    """L1 on white of the one-step render with ``code`` against the input image."""
    from train.losses.metrics import composite_on_white

    with torch.no_grad():
        maps = model(code, batch["in_pose"], batch["in_gaze_head"], batch["in_viewmat"], batch["K"], 64, 64,
                     renders=("head",))
        out = renderer.render(maps["head"], code, gaze=batch["in_gaze_head"], pose=batch["in_pose"])
    return float((composite_on_white(out, mask) - composite_on_white(image, mask)).abs().mean())
