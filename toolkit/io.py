"""Atomic file writes and safetensors checkpoints.

Every artefact the project writes goes through :func:`atomic_write` (or a helper built on it), or through
:func:`atomic_path` for writers that take a file name (OpenCV's video writer): data go
to a temporary file in the destination's folder, are flushed and fsynced, then renamed over the target,
so a crash or Ctrl-C never leaves a half-written file behind. Weights are safetensors; foreign torch
checkpoints are read only with ``weights_only=True``.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import socket
import tempfile
import warnings
from pathlib import Path
from typing import IO, Any, Iterator, Mapping

import torch

from toolkit.errors import ToolkitError, one_line
from toolkit.limits import check_allocation


def _process_umask() -> int:
    mask = os.umask(0)  # reading the umask means setting it: put it straight back
    os.umask(mask)
    return mask


_UMASK = _process_umask()  # once, at import: a later read would briefly zero the mask under other threads


def _new_file_mode(path: Path) -> int:
    """The mode ``open(path, "w")`` would leave: the existing file's, else 0o666 less the umask (mkstemp's
    temporary files are 0o600, which would hide every output from the user's group)."""
    try:
        return path.stat().st_mode & 0o7777
    except OSError:
        return 0o666 & ~_UMASK


def _writer_tag() -> str:
    """This process's mark in its temporary files' names: the host and the process id."""
    return f"{socket.gethostname().replace('.', '-')}-{os.getpid()}"


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def remove_stale_temps(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary files in ``folder`` that a writer on this host left when it was killed mid-write
    (``.NAME.HOST-PID.*.tmp`` whose process is gone); a live writer's, or another host's, are kept. Returns
    what was removed."""
    host = _writer_tag().rsplit("-", 1)[0]
    removed = []
    for tmp in Path(folder).glob(f".*.{host}-*.tmp"):
        pid = tmp.name[tmp.name.index(f".{host}-") + len(host) + 2:].split(".", 1)[0]
        if pid.isdigit() and not _process_alive(int(pid)):
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
                removed.append(tmp)
    return removed


# A write that the file system refuses for room: one line naming the destination, whatever layer raised it.
_FULL = {errno.ENOSPC: "no space left on device", errno.EDQUOT: "disk quota exceeded",
         errno.EFBIG: "file too large for this file system or process limit"}


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[Path]:
    """A temporary file name beside ``path`` (ending in ``suffix``), for writers that take a file name; on clean
    exit the file is given ``path``'s mode, fsynced and renamed onto ``path``, else deleted. The name carries
    the writer's host and process id, so that a later write to the folder removes what a killed writer left
    (:func:`remove_stale_temps`)."""
    path = Path(path)
    if path.is_dir():
        raise ToolkitError(f"{path}: is a directory, expected a file path to write")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(path.parent)  # a killed writer's leftovers: the next write to the folder clears them
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{_writer_tag()}.", suffix=suffix, dir=path.parent)
    except OSError as e:  # a parent that is a file, a read-only or missing mount, no permission
        raise ToolkitError(f"{path}: cannot write here ({e.strerror or e})") from None
    try:
        try:
            os.fchmod(fd, _new_file_mode(path))
        finally:
            os.close(fd)
        yield Path(tmp)
        fd = os.open(tmp, os.O_RDONLY)  # fsync flushes the file's data whichever descriptor asks
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(e, OSError) and e.errno in _FULL:
            raise ToolkitError(f"{path}: {_FULL[e.errno]}; nothing was written (the partial file was removed)") from None
        raise


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path``; on clean exit rename it onto ``path``, else delete it. Text modes
    write UTF-8 whatever the locale (reports hold degree signs)."""
    with atomic_path(path) as tmp, open(tmp, mode, encoding=None if "b" in mode else "utf-8") as f:
        yield f


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_write(path, "wb") as f:
        f.write(data)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_write(path, "w") as f:
        f.write(text)


@contextlib.contextmanager
def atomic_h5(path: str | os.PathLike) -> Iterator[Any]:
    """An ``h5py.File`` built in memory, written to ``path`` through :func:`atomic_write_bytes` when the block
    exits cleanly (nothing is written otherwise). HDF5 never writes to disk itself: through h5py a full disk
    makes the library fail inside its own clean-up and crash the interpreter; here a full disk is the one
    ``ToolkitError`` of :func:`atomic_path`. The file's image is held in memory: callers bound what they put in."""
    import h5py

    f = h5py.File(f"{path}.{id(object())}", "w", driver="core", backing_store=False)  # the name is only a label
    try:
        yield f
        f.flush()
        image = f.id.get_file_image()
    finally:
        f.close()
    atomic_write_bytes(path, image)


def atomic_write_json(path: str | os.PathLike, obj: Any, *, strict: bool = False) -> None:
    """``obj`` as indented JSON; ``strict``: NaN and ±inf written as null (Python's JSON writes them as the
    non-standard NaN / Infinity, which strict parsers refuse)."""
    if strict:
        obj = finite_json(obj)
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, allow_nan=not strict) + "\n")


def finite_json(obj: Any) -> Any:
    """``obj`` (JSON values: dicts, lists, tuples, numbers, strings) with every NaN or ±inf float as None."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    return obj


def check_readable_file(path: str | os.PathLike, what: str = "file") -> Path:
    """Return ``Path(path)`` or raise a ToolkitError saying why it cannot be read as a ``what``."""
    path = Path(path)
    if not path.exists():
        raise ToolkitError(f"{path}: no such {what}")
    if path.is_dir():
        raise ToolkitError(f"{path}: is a directory, expected a {what}")
    if not os.access(path, os.R_OK):
        raise ToolkitError(f"{path}: not readable")
    return path


def check_output_folder(folder: str | os.PathLike, what: str, *, writable: bool = True) -> Path:
    """``folder``, an output folder a command makes later, once it is a folder or can be made: its nearest existing
    ancestor is a folder (``writable``: one this process may write in). A ToolkitError naming ``what`` (the flag)
    otherwise, before any work rather than at the first write, after the inputs were read."""
    folder = Path(folder)
    up = next((q for q in (folder, *folder.parents) if q.exists()), None)
    if up is not None and not up.is_dir():
        raise ToolkitError(f"{what}: {up} is a file, not a folder")
    if writable and up is not None and not os.access(up, os.W_OK | os.X_OK):
        raise ToolkitError(f"{what}: cannot write in the folder {up} (no permission)")
    return folder


def check_device(device: str | torch.device, what: str = "device", *, auto: bool = False) -> torch.device:
    """``device`` as a ``torch.device``: a name torch knows, and for cuda[:N] CUDA present with GPU N among its
    GPUs; else a ToolkitError naming ``what``. ``auto``: "auto" is accepted too (CUDA when available, else the
    CPU), and the messages offer it, in the words of a run config's ``device`` key."""
    if auto and isinstance(device, str) and device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        names = "'auto', 'cpu', 'cuda' or 'cuda:N'" if auto else "cpu, cuda or cuda:N"
        raise ToolkitError(f"{what}: expected {names}, got {device!r}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        if auto:
            raise ToolkitError(f"{what}=cuda but CUDA is not available; use {what}=cpu or {what}=auto")
        raise ToolkitError(f"{what} {device}: CUDA is not available here (no GPU, or a CPU build of torch); use cpu")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ToolkitError(f"{what} {device}: this machine has {torch.cuda.device_count()} GPU(s)")
    return dev


def nonfinite_tensors(state: Mapping[str, torch.Tensor]) -> list[str]:
    """The names, in order, of the floating-point tensors of ``state`` holding NaN or inf: loaded weights are
    scanned with it so that a damaged file is named when read, not later as a diverged result."""
    return [k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]


def check_not_an_input(output: str | os.PathLike, inputs: list[str | os.PathLike], flag: str = "output",
                       kind: str = "file") -> None:
    """A ToolkitError, before any work, when writing ``output`` would replace what the command reads: ``inputs``
    lists every file and folder it reads (a folder's files that it reads among them); paths are compared
    resolved, links followed."""
    out = Path(output).resolve()
    for given in inputs:
        if out == Path(given).resolve():
            raise ToolkitError(f"{flag} {output}: is the input {kind} ({given}); writing it would replace it, give "
                               "another path")


def save_tensors(path: str | os.PathLike, tensors: dict[str, torch.Tensor], metadata: dict[str, Any] | None = None) -> None:
    """Write tensors as safetensors with JSON-encodable ``metadata`` stored under the key ``"json"``."""
    from safetensors.torch import save as st_save

    clean = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    try:
        meta = {"json": json.dumps(metadata or {}, sort_keys=True)}
    except (TypeError, ValueError) as e:  # a tensor or other object among the values, a circular reference
        raise ToolkitError(f"{path}: metadata must hold JSON values only ({one_line(e)}); nothing was written") \
            from None
    atomic_write_bytes(path, st_save(clean, metadata=meta))


def load_tensors(path: str | os.PathLike, device: str | torch.device = "cpu") -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Read a safetensors file written by :func:`save_tensors` -> (tensors, metadata)."""
    return _read(path, device, tensors=True)


def load_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The metadata of a safetensors file written by :func:`save_tensors`, without reading its tensors."""
    return _read(path, "cpu", tensors=False)[1]


MAX_JSON_DEPTH = 64
"""Deepest nesting a file's JSON metadata may have: copying or re-encoding it recurses once per level, so a
forged file nested thousands deep would be a RecursionError far from the reader (as ``toolkit.safe_yaml``)."""


_JSON_NAMES = {list: "array", str: "string", int: "number", float: "number", bool: "boolean", type(None): "null"}


def json_depth(obj: Any) -> int:
    """Nesting depth of a parsed JSON value (a scalar is 0), counted without recursion."""
    deepest, todo = 0, [(obj, 0)]
    while todo:
        item, depth = todo.pop()
        if isinstance(item, (dict, list)):
            deepest = max(deepest, depth + 1)
            if depth + 1 > MAX_JSON_DEPTH:
                break  # already too deep: no need to walk the rest
            todo += [(v, depth + 1) for v in (item.values() if isinstance(item, dict) else item)]
    return deepest


def parse_json_object(text: str | bytes, where: str) -> dict[str, Any]:
    """``text`` parsed as a JSON object of bounded depth, else one ToolkitError "``where`` is not ..." (``where``
    names the file and the field)."""
    try:
        obj = json.loads(text)
    except RecursionError:  # json's C scanner recurses once per level and refuses past the recursion limit
        raise ToolkitError(f"{where} is JSON nested deeper than {MAX_JSON_DEPTH} levels") from None
    except (ValueError, UnicodeDecodeError) as e:  # JSONDecodeError, and integers over Python's digit limit
        raise ToolkitError(f"{where} is not valid JSON ({one_line(e)})") from None
    if not isinstance(obj, dict):
        raise ToolkitError(f"{where} is not a JSON object (got a JSON {_JSON_NAMES.get(type(obj), type(obj).__name__)})")
    if json_depth(obj) > MAX_JSON_DEPTH:
        raise ToolkitError(f"{where} is JSON nested deeper than {MAX_JSON_DEPTH} levels")
    return obj


def _read(path, device, tensors: bool) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The one safetensors reader. The library (0.8, as tested) itself refuses, as ``SafetensorError``: a file
    under 8 bytes, a header length (the first 8 bytes) past the file's end or over its header limit, a header
    that is not JSON or not a map of string metadata and tensor entries, an unknown dtype, a negative shape
    or one whose byte size overflows, and tensor byte ranges that overlap, leave gaps, miss or overrun the
    file's end, or differ from dtype x shape. It memory-maps the file, so none of that allocates; each of its
    errors is wrapped here into one line naming the file (and the tensor, when one fails to load)."""
    from safetensors import safe_open

    check_device(device)
    path = check_readable_file(path, "safetensors file")
    if tensors:  # the tensors' bytes lie in the file (checked by the library), so the file's size bounds them
        check_allocation(path.stat().st_size, f"{path}: reading its tensors")
    name = None
    try:
        with safe_open(str(path), framework="pt", device=str(device)) as f:
            raw_meta = f.metadata() or {}
            out = {}
            for name in f.keys() if tensors else ():
                out[name] = f.get_tensor(name)
    except Exception as e:  # SafetensorError, or torch refusing a dtype it lacks or a device it has not
        what = f": tensor {name!r}" if name is not None else ""
        raise ToolkitError(f"{path}: not a valid safetensors file{what} ({type(e).__name__}: {one_line(e)})") \
            from None
    meta = parse_json_object(raw_meta.get("json", "{}"), f"{path}: metadata 'json'")
    return out, meta


def save_checkpoint(path: str | os.PathLike, state_dict: dict[str, torch.Tensor], info: dict[str, Any] | None = None) -> None:
    """Atomically write a model ``state_dict`` (safetensors) with JSON ``info`` (config, step, ...).

    Tied weights are stored once per name (cloned), so safetensors' shared-memory check never trips.
    """
    tensors = {k: v.detach().clone() for k, v in state_dict.items() if isinstance(v, torch.Tensor)}
    save_tensors(path, tensors, info)


def load_checkpoint(path: str | os.PathLike, device: str | torch.device = "cpu") -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Read a checkpoint written by :func:`save_checkpoint` -> (state_dict, info)."""
    return load_tensors(path, device)


def file_stamp(path: str | os.PathLike) -> str:
    """``path resolved:size:mtime_ns`` -- what tells a file replaced or edited under the same name, cheaply."""
    path = Path(path)
    st = path.stat()
    return f"{path.resolve()}:{st.st_size}:{st.st_mtime_ns}"


def load_state_dict_file(path: str | os.PathLike) -> dict:
    """A third-party weight file as a dict: ``.safetensors`` (:func:`load_tensors`), else a ``.pt``/``.pth``
    read weights-only (:func:`load_foreign_torch_checkpoint`); anything but a dict is a ToolkitError."""
    path = Path(path)
    try:
        state = load_tensors(path)[0] if path.suffix.lower() == ".safetensors" else load_foreign_torch_checkpoint(path)
    except ToolkitError as e:  # torch's unpickling errors span several lines: the promise is one
        raise ToolkitError(one_line(e, limit=400)) from None
    if not isinstance(state, dict):
        raise ToolkitError(f"{path}: expected a state dict (name -> tensor), got {type(state).__name__}")
    return state


def load_foreign_torch_checkpoint(path: str | os.PathLike) -> Any:
    """Read a third-party ``.pt``/``.pth`` file safely (``weights_only=True``: no arbitrary pickles)."""
    path = check_readable_file(path, "torch checkpoint")
    try:
        with warnings.catch_warnings():  # torch warns of an unusual pickle protocol; the refusal below says it
            warnings.simplefilter("ignore", UserWarning)
            return torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as e:
        raise ToolkitError(
            f"{path}: could not be read as a weights-only torch checkpoint ({type(e).__name__}: {one_line(e, 160)})"
        ) from None
