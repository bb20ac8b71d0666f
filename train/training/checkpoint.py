"""Atomic, resumable training checkpoints: safetensors for every tensor, JSON for everything else.

A checkpoint holds modules, optimizers (their state tensors flattened by name), the step and the RNG
states, so a resumed CPU run continues bit-for-bit where the uninterrupted one would be. Files are
``ckpt_{step:08d}.safetensors`` in one folder; the newest ``keep`` are kept. Writes are atomic, so a
crash or SIGKILL mid-save leaves the previous checkpoint intact (at most one interval is lost).
"""

from __future__ import annotations

import random
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from toolkit.errors import ToolkitError
from toolkit.io import load_metadata, load_tensors, save_tensors

_NAME = re.compile(r"ckpt_(\d{8})\.safetensors$")


def _flatten_optimizer(prefix: str, opt: torch.optim.Optimizer, tensors: dict, meta: dict) -> None:
    sd = opt.state_dict()
    scalars: dict[str, dict[str, Any]] = {}
    for pid, st in sd["state"].items():
        for k, v in st.items():
            if isinstance(v, torch.Tensor):
                tensors[f"{prefix}/state/{pid}/{k}"] = v
            else:
                scalars.setdefault(str(pid), {})[k] = v
    meta[prefix] = {"param_groups": sd["param_groups"], "scalars": scalars}


def _unflatten_optimizer(prefix: str, tensors: dict, meta: dict) -> dict:
    state: dict[int, dict[str, Any]] = {}
    for name, t in tensors.items():
        if name.startswith(prefix + "/state/"):
            pid, k = name[len(prefix) + 7:].split("/", 1)
            state.setdefault(int(pid), {})[k] = t
    for pid, sc in meta[prefix]["scalars"].items():
        state.setdefault(int(pid), {}).update(sc)
    return {"state": state, "param_groups": meta[prefix]["param_groups"]}


def rng_state() -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    tensors = {"rng/torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        for i, s in enumerate(torch.cuda.get_rng_state_all()):
            tensors[f"rng/cuda{i}"] = s
    np_state = np.random.get_state()
    meta = {"python": _to_json(random.getstate()), "numpy": [np_state[0], np_state[1].tolist(), *np_state[2:]]}
    return tensors, meta


def _to_json(obj: Any) -> Any:
    if isinstance(obj, tuple):
        return [_to_json(x) for x in obj]
    return obj


def _from_json(obj: Any) -> Any:
    if isinstance(obj, list):
        return tuple(_from_json(x) for x in obj)
    return obj


def set_rng_state(tensors: dict[str, torch.Tensor], meta: dict[str, Any]) -> None:
    torch.set_rng_state(tensors["rng/torch"])
    if torch.cuda.is_available():
        states = [tensors[k] for k in sorted(k for k in tensors if k.startswith("rng/cuda"))]
        if states:
            torch.cuda.set_rng_state_all(states)
    random.setstate(_from_json(meta["python"]))
    n = meta["numpy"]
    np.random.set_state((n[0], np.array(n[1], dtype=np.uint32), *n[2:]))


def save_training_checkpoint(
    path: str | Path,
    *,
    step: int,
    modules: dict[str, torch.nn.Module],
    optimizers: dict[str, torch.optim.Optimizer] | None = None,
    extra: dict[str, Any] | None = None,
) -> None:
    tensors: dict[str, torch.Tensor] = {}
    meta: dict[str, Any] = {"step": step, "extra": extra or {}, "modules": sorted(modules),
                            "optimizers": sorted(optimizers or {})}
    for name, m in modules.items():
        for k, v in m.state_dict().items():
            tensors[f"module/{name}/{k}"] = v.detach().clone()
    opt_meta: dict[str, Any] = {}
    for name, opt in (optimizers or {}).items():
        _flatten_optimizer(f"optim/{name}", opt, tensors, opt_meta)
    meta["optim"] = opt_meta
    rt, rm = rng_state()
    tensors.update(rt)
    meta["rng"] = rm
    save_tensors(path, tensors, meta)


def load_training_checkpoint(
    path: str | Path,
    *,
    modules: dict[str, torch.nn.Module],
    optimizers: dict[str, torch.optim.Optimizer] | None = None,
    restore_rng: bool = True,
) -> dict[str, Any]:
    """Restore modules/optimizers (and RNG) in place; returns ``{"step": .., "extra": ..}``.

    A checkpoint of another model configuration (missing/unexpected keys, shape mismatch) is a clear
    ``ToolkitError`` naming the module and the first offending parameter.
    """
    tensors, meta = load_tensors(path)
    if "step" not in meta or "modules" not in meta:
        raise ToolkitError(f"{path}: not a training checkpoint (no step/modules in its metadata)")
    for name, m in modules.items():
        prefix = f"module/{name}/"
        sd = {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
        if not sd:
            raise ToolkitError(f"{path}: has no weights for module '{name}' (it holds {meta['modules']})")
        own = m.state_dict()
        missing = sorted(set(own) - set(sd))
        unexpected = sorted(set(sd) - set(own))
        if missing or unexpected:
            raise ToolkitError(
                f"{path}: incompatible checkpoint for '{name}' (another model configuration?): "
                f"missing {missing[:3]}, unexpected {unexpected[:3]}"
            )
        for k, v in sd.items():
            if own[k].shape != v.shape:
                raise ToolkitError(
                    f"{path}: incompatible checkpoint for '{name}': '{k}' has shape {list(v.shape)}, "
                    f"the model expects {list(own[k].shape)} (another model configuration?)"
                )
        m.load_state_dict(sd)
    for name, opt in (optimizers or {}).items():
        key = f"optim/{name}"
        if key not in meta.get("optim", {}):
            raise ToolkitError(f"{path}: has no state for optimizer '{name}'")
        try:
            opt.load_state_dict(_unflatten_optimizer(key, tensors, meta["optim"]))
        except (ValueError, KeyError, TypeError) as e:  # another grouping of the parameters, say
            raise ToolkitError(f"{path}: incompatible state for optimizer '{name}' ({str(e).splitlines()[0][:160]})") from None
    if restore_rng:
        if "rng" not in meta:
            raise ToolkitError(f"{path}: has no random-number state to resume from (metadata key 'rng')")
        set_rng_state(tensors, meta["rng"])
    return {"step": int(meta["step"]), "extra": meta.get("extra", {})}


class CheckpointManager:
    """Numbered checkpoints in ``folder``; keeps the newest ``keep``; finds the latest readable one."""

    def __init__(self, folder: str | Path, keep: int = 2):
        self.folder = Path(folder)
        self.keep = max(1, keep)
        self.skipped: list[Path] = []
        """the unreadable checkpoints the last :meth:`latest` passed over"""

    def path_for(self, step: int) -> Path:
        return self.folder / f"ckpt_{step:08d}.safetensors"

    def all(self) -> list[Path]:
        if not self.folder.is_dir():
            return []
        return sorted((p for p in self.folder.iterdir() if _NAME.search(p.name)), key=lambda p: p.name)

    def latest(self) -> Path | None:
        """The newest checkpoint whose header reads (writes are atomic, so an unreadable one was damaged
        afterwards: the one before it is the one to resume from)."""
        self.skipped = []
        for p in reversed(self.all()):
            try:
                load_metadata(p)
            except ToolkitError:
                self.skipped.append(p)
                continue
            return p
        return None

    def save(self, step: int, **kwargs: Any) -> Path:
        path = self.path_for(step)
        save_training_checkpoint(path, step=step, **kwargs)
        for old in self.all()[: -self.keep]:
            old.unlink(missing_ok=True)
        return path
