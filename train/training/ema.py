"""An exponential moving average of a module's weights (Polyak averaging), as DiT trains its models.

The average is a frozen copy of the module: ``update_average`` moves each of its trained parameters a share
``1 - decay`` of the way to the live parameter after an optimizer step, and copies the frozen parameters and
the buffers as they are. With a constant decay d the copy weighs the step k updates back by (1 - d) d^k, a horizon of about
1 / (1 - d) steps; the initial weights keep a share d^n after n updates.

Being a module, the copy goes into the training checkpoints beside the live one, so a resumed run continues
the same average.
"""

from __future__ import annotations

import copy

import torch


def averaged_copy(module: torch.nn.Module) -> torch.nn.Module:
    """A frozen deep copy of ``module`` to hold its average (no parameter of it requires a gradient)."""
    avg = copy.deepcopy(module)
    avg.requires_grad_(False)
    return avg


@torch.no_grad()
def update_average(avg: torch.nn.Module, live: torch.nn.Module, decay: float) -> None:
    """avg ← decay · avg + (1 − decay) · live for every trained parameter; frozen parameters and buffers are
    copied (x · d + x · (1 − d) is not exactly x in float, and a frozen codec should stay bit for bit the one
    it was loaded from). ``decay`` in [0, 1)."""
    avg_params = dict(avg.named_parameters())
    for name, p in live.named_parameters():
        if not p.requires_grad:
            avg_params[name].copy_(p)
            continue
        # Scale then add, not lerp: lerp's (live - avg) overflows for weights of opposite sign near the float max.
        avg_params[name].mul_(decay).add_(p.detach(), alpha=1.0 - decay)
    avg_buffers = dict(avg.named_buffers())
    for name, b in live.named_buffers():
        avg_buffers[name].copy_(b)
