"""Atomic, resumable training checkpoints: safetensors for every tensor, JSON for everything else.

A checkpoint holds modules, optimizers (their state tensors flattened by name), the step and the RNG
states, so a resumed CPU run continues bit-for-bit where the uninterrupted one would be. Files are
``ckpt_{step:08d}.safetensors`` in one folder; the newest ``keep`` are kept. Writes are atomic, so a
crash or SIGKILL mid-save leaves the previous checkpoint intact (at most one interval is lost).
"""

from __future__ import annotations

import json
import os
import random
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from toolkit.errors import ToolkitError, one_line
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


def _check_rng_state(path: str | Path, meta: dict[str, Any], tensors: dict[str, torch.Tensor] | None) -> None:
    """Try a checkpoint's random-number states on throwaway generators, so a malformed one is refused as one line
    before anything is restored (the global generators' setters raise Python errors half-way otherwise)."""
    if "rng" not in meta:
        raise ToolkitError(f"{path}: has no random-number state to resume from (metadata key 'rng')")
    rng = meta["rng"]
    try:
        random.Random().setstate(_from_json(rng["python"]))
        n = rng["numpy"]
        np.random.RandomState().set_state((n[0], np.array(n[1], dtype=np.uint32), *n[2:]))
        if tensors is not None:
            torch.Generator().set_state(tensors["rng/torch"])
    except (TypeError, ValueError, KeyError, IndexError, OverflowError, RuntimeError) as e:
        raise ToolkitError(f"{path}: metadata 'rng' must be the random-number states a checkpoint records "
                           f"(python, numpy, and the tensor 'rng/torch'), got {_shown(rng)} "
                           f"({type(e).__name__}: {one_line(e, limit=120)})") from None


def _shown(value: Any) -> str:
    """A metadata value as its JSON, cut short: a random-number state alone is thousands of numbers."""
    text = json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


def check_checkpoint_metadata(path: str | Path, meta: dict[str, Any], *, rng: bool = True) -> None:
    """Refuse, as one line naming the file and the field, metadata that is not what
    :func:`save_training_checkpoint` writes: the file is then a forgery or was edited, and reading it on
    would fail deep in a load with a Python error. ``rng``: its random-number state is needed too."""
    if "step" not in meta or "modules" not in meta:
        raise ToolkitError(f"{path}: not a training checkpoint (no step/modules in its metadata)")

    def expect(field: str, ok: bool, what: str) -> None:
        if not ok:
            raise ToolkitError(f"{path}: metadata '{field}' must be {what}, got {_shown(meta[field])}")

    step = meta["step"]
    expect("step", isinstance(step, int) and not isinstance(step, bool) and step >= 0, "a step count (a whole number >= 0)")
    expect("modules", isinstance(meta["modules"], list) and all(isinstance(m, str) for m in meta["modules"]),
           "a list of module names")
    expect("extra", isinstance(meta.setdefault("extra", {}), dict), "a JSON object")
    optim = meta.setdefault("optim", {})
    expect("optim", isinstance(optim, dict) and all(
        isinstance(o, dict) and isinstance(o.get("param_groups"), list) and isinstance(o.get("scalars"), dict)
        and all(isinstance(sc, dict) for sc in o["scalars"].values()) for o in optim.values()),
        "a JSON object of optimizer states (each with a list 'param_groups' and an object 'scalars')")
    if rng:
        _check_rng_state(path, meta, None)


def checkpoint_metadata(path: str | Path, *, rng: bool = True) -> dict[str, Any]:
    """The metadata of the training checkpoint ``path``, checked (:func:`check_checkpoint_metadata`)."""
    meta = load_metadata(path)
    check_checkpoint_metadata(path, meta, rng=rng)
    return meta


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
    check_checkpoint_metadata(path, meta, rng=False)
    if restore_rng:  # checked before any module is loaded, so a refusal leaves them as they were
        _check_rng_state(path, meta, tensors)
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
        if key not in meta["optim"]:
            raise ToolkitError(f"{path}: has no state for optimizer '{name}'")
        try:
            opt.load_state_dict(_unflatten_optimizer(key, tensors, meta["optim"]))
        except (ValueError, KeyError, TypeError, AttributeError, IndexError) as e:  # another grouping, say
            raise ToolkitError(f"{path}: incompatible state for optimizer '{name}' ({str(e).splitlines()[0][:160]})") from None
    if restore_rng:
        set_rng_state(tensors, meta["rng"])
    return {"step": meta["step"], "extra": meta["extra"]}


class CheckpointManager:
    """Numbered checkpoints in ``folder``; keeps the newest ``keep``; finds the latest readable one."""

    def __init__(self, folder: str | Path, keep: int = 2):
        self.folder = Path(folder)
        self.keep = max(1, keep)
        self.skipped: list[Path] = []
        """the unreadable checkpoints the last :meth:`newest` passed over"""
        self.reasons: dict[Path, str] = {}
        """why each of :attr:`skipped` could not be read"""

    def path_for(self, step: int) -> Path:
        return self.folder / f"ckpt_{step:08d}.safetensors"

    def all(self) -> list[Path]:
        if not self.folder.is_dir():
            return []
        return sorted((p for p in self.folder.iterdir() if _NAME.search(p.name)), key=lambda p: p.name)

    def check_files(self) -> None:
        """Refuse a directory (or a link to nothing, a device...) with a checkpoint's name, before any training:
        it is no checkpoint to resume, and saving over it, or clearing it for a fresh run, would fail later."""
        for p in self.all():
            # An entry gone since the listing (another rank clearing the folder for a fresh run) is no problem.
            if not p.is_file() and (p.is_dir() or os.path.lexists(p)):
                kind = "a directory" if p.is_dir() else "a broken link" if p.is_symlink() else "no regular file"
                raise ToolkitError(f"{p}: is {kind}, expected a checkpoint file (the training saves its checkpoints "
                                   "under this name); move it out of the checkpoint folder")

    def newest(self) -> tuple[Path, dict[str, Any]] | None:
        """``(path, checked metadata)`` of the newest checkpoint whose header and metadata read (writes are
        atomic, so an unreadable one was damaged afterwards: the one before it is the one to resume from). A
        checkpoint whose recorded step is not the one its name says (a copy under another name) is refused:
        resuming it would start at one step and replay the data of the other, and its name would keep it the
        newest however long the run trained. Callers that resume check the folder first (:meth:`check_files`)."""
        self.skipped, self.reasons = [], {}
        for p in reversed(self.all()):
            try:
                meta = checkpoint_metadata(p)
            except ToolkitError as e:
                self.skipped.append(p)
                self.reasons[p] = str(e)
                continue
            named = int(_NAME.search(p.name).group(1))
            if meta["step"] != named:
                raise ToolkitError(f"{p}: its name says step {named} but its metadata records step {meta['step']} "
                                   f"(a copy?); rename it to {self.path_for(meta['step']).name} or remove it")
            return p, meta
        return None

    def resume_from(self) -> tuple[Path, dict[str, Any]] | None:
        """:meth:`newest`, None for a folder without checkpoints; refused when there are checkpoints but none
        reads, before any training: resuming from the start would delete them with its first save."""
        found = self.newest()
        if found is None and self.skipped:
            first = self.skipped[-1]
            raise ToolkitError(f"{self.folder}: none of its checkpoints can be read "
                               f"({', '.join(p.name for p in reversed(self.skipped))}; {self.reasons[first]}); "
                               "remove them to train the stage afresh, or rerun without --resume")
        return found

    def save(self, step: int, **kwargs: Any) -> Path:
        path = self.path_for(step)
        save_training_checkpoint(path, step=step, **kwargs)
        for old in self.all()[: -self.keep]:
            old.unlink(missing_ok=True)
        return path
