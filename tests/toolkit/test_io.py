import pytest
import torch

from toolkit import ToolkitError
from toolkit.io import (
    atomic_write,
    atomic_write_json,
    check_device,
    check_output_folder,
    load_checkpoint,
    load_foreign_torch_checkpoint,
    load_state_dict_file,
    nonfinite_tensors,
    save_checkpoint,
)


def test_atomic_write_cleans_up_on_error(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_write(target) as f:
            f.write(b"new partial")
            raise RuntimeError("crash mid-write")
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bin"]


def test_nonfinite_tensors_names_the_floating_tensors_with_nan_or_inf_in_order():
    state = {"ok": torch.ones(3), "nan": torch.tensor([1.0, float("nan")]), "steps": torch.tensor([7]),
             "inf": torch.tensor([float("-inf")], dtype=torch.float64), "empty": torch.zeros(0)}
    assert nonfinite_tensors(state) == ["nan", "inf"]
    assert nonfinite_tensors({}) == []


def test_a_run_configs_device_may_be_auto():
    """``auto=True`` (a run's ``device`` key) takes "auto" and offers it in its messages; plain names are kept."""
    assert check_device("auto", auto=True) == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert check_device("cpu", auto=True) == torch.device("cpu")
    with pytest.raises(ToolkitError, match=r"^device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got 'auto!'$"):
        check_device("auto!", auto=True)
    with pytest.raises(ToolkitError, match=r"^device: expected cpu, cuda or cuda:N, got 'auto'$"):
        check_device("auto")


def test_atomic_write_under_a_file_is_one_clear_error(tmp_path):
    (tmp_path / "blocker").write_text("a file, not a folder")
    with pytest.raises(ToolkitError, match=r"blocker/out.json: cannot write here"):
        atomic_write_json(tmp_path / "blocker" / "out.json", {"a": 1})


def test_an_output_folder_is_checked_before_it_is_made(tmp_path):
    """A folder to be made later passes when it or its nearest existing ancestor is a folder; a file on its way is
    named, and nothing is created by the check."""
    assert check_output_folder(tmp_path / "a" / "b", "--out") == tmp_path / "a" / "b"
    assert not (tmp_path / "a").exists()
    (tmp_path / "f").write_text("a file")
    for folder in (tmp_path / "f", tmp_path / "f" / "sub" / "deeper"):
        with pytest.raises(ToolkitError, match=rf"^--out x: {tmp_path}/f is a file, not a folder$"):
            check_output_folder(folder, "--out x")


def test_strict_json_writes_nan_and_infinity_as_null(tmp_path):
    """One repetition's interval is infinite: strict JSON parsers refuse Python's Infinity, so it becomes null."""
    import json
    import math

    def refuse(name):
        raise ValueError(f"non-standard JSON constant {name}")

    obj = {"lo": -math.inf, "hi": math.inf, "x": [1.5, math.nan, (2, "a")], "n": 1}
    atomic_write_json(tmp_path / "s.json", obj, strict=True)
    assert json.loads((tmp_path / "s.json").read_text(), parse_constant=refuse) == {
        "lo": None, "hi": None, "x": [1.5, None, [2, "a"]], "n": 1}
    atomic_write_json(tmp_path / "loose.json", obj)  # the default keeps Python's constants
    assert "Infinity" in (tmp_path / "loose.json").read_text()


def test_metadata_that_is_not_an_object_is_refused(tmp_path):
    from safetensors.torch import save_file

    from toolkit.io import load_tensors

    save_file({"w": torch.ones(2)}, str(tmp_path / "m.safetensors"), metadata={"json": "[1]"})
    with pytest.raises(ToolkitError, match="metadata 'json' is not a JSON object"):
        load_tensors(tmp_path / "m.safetensors")


def test_metadata_alone_reads_as_with_the_tensors(tmp_path):
    from toolkit.io import load_metadata, load_tensors, save_tensors

    save_tensors(tmp_path / "t.safetensors", {"w": torch.ones(3)}, {"step": 7, "modules": ["model"]})
    assert load_metadata(tmp_path / "t.safetensors") == load_tensors(tmp_path / "t.safetensors")[1] == {
        "step": 7, "modules": ["model"]}
    (tmp_path / "bad.safetensors").write_bytes(b"garbage")
    with pytest.raises(ToolkitError, match="bad.safetensors: not a valid safetensors file"):
        load_metadata(tmp_path / "bad.safetensors")


def test_atomic_path_hands_a_name_and_renames_only_on_success(tmp_path):
    from toolkit.io import atomic_path

    target = tmp_path / "v.mp4"
    with atomic_path(target, suffix=".mp4") as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".mp4" and not target.exists()
        tmp.write_bytes(b"new")
    assert target.read_bytes() == b"new"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("crash mid-write")
    assert target.read_bytes() == b"new" and sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]


def test_checkpoint_round_trip_with_tied_weights(tmp_path):
    lin = torch.nn.Linear(3, 3)
    sd = {"a": lin.weight, "b": lin.weight, "c": torch.arange(4)}
    save_checkpoint(tmp_path / "c.safetensors", sd, {"step": 3, "config": {"w": 1}})
    sd2, info = load_checkpoint(tmp_path / "c.safetensors")
    assert info == {"step": 3, "config": {"w": 1}}
    assert torch.equal(sd2["a"], lin.weight.detach()) and torch.equal(sd2["c"], torch.arange(4))
    atomic_write_json(tmp_path / "x.json", {"b": 1})
    assert (tmp_path / "x.json").read_text().startswith("{")


def test_foreign_checkpoint_weights_only(tmp_path):
    torch.save({"w": torch.ones(2)}, tmp_path / "ok.pt")
    assert torch.equal(load_foreign_torch_checkpoint(tmp_path / "ok.pt")["w"], torch.ones(2))

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    torch.save({"x": Evil()}, tmp_path / "evil.pt")
    with pytest.raises(ToolkitError, match="weights-only"):
        load_foreign_torch_checkpoint(tmp_path / "evil.pt")
    with pytest.raises(ToolkitError, match="no such"):
        load_foreign_torch_checkpoint(tmp_path / "missing.pt")


def test_atomic_write_leaves_the_mode_a_plain_write_would(tmp_path, monkeypatch):
    """Not mkstemp's 0o600: a new file gets 0o666 less the umask, a replaced file keeps its own mode."""
    import os
    import stat

    import toolkit.io

    monkeypatch.setattr(toolkit.io, "_UMASK", 0o022)  # the module reads the process's umask once, at import
    toolkit.io.atomic_write_text(tmp_path / "new.txt", "a")
    assert stat.S_IMODE((tmp_path / "new.txt").stat().st_mode) == 0o644
    (tmp_path / "kept.txt").write_text("b")
    os.chmod(tmp_path / "kept.txt", 0o640)
    toolkit.io.atomic_write_text(tmp_path / "kept.txt", "c")
    assert stat.S_IMODE((tmp_path / "kept.txt").stat().st_mode) == 0o640
    assert (tmp_path / "kept.txt").read_text() == "c"
    assert toolkit.io._UMASK == os.umask(toolkit.io._UMASK)  # and the read left the umask as it was


def test_text_is_written_as_utf8_whatever_the_locale(tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    code = (f"import sys; sys.path.insert(0, {str(root)!r}); from toolkit.io import atomic_write_text; "
            f"atomic_write_text({str(tmp_path / 'r.md')!r}, '5.2\\u00b0 \\u00b1 0.2\\u00b0')")
    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONIOENCODING": "ascii"}
    r = subprocess.run([sys.executable, "-X", "utf8=0", "-c", code], env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "r.md").read_bytes() == "5.2° ± 0.2°".encode("utf-8")


def test_a_killed_writers_temp_file_is_removed_by_the_next_write(tmp_path):
    """A writer killed mid-write leaves ``.NAME.HOST-PID.*.tmp``; the next write to that folder removes it, while
    a live writer's temp file (this process's) and another host's stay."""
    import os
    import socket
    import subprocess
    import sys

    from toolkit.io import atomic_write_bytes

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    host = socket.gethostname().replace(".", "-")
    stale = tmp_path / f".ckpt_00000004.safetensors.{host}-{dead.pid}.abc123.tmp"
    live = tmp_path / f".subject0000.h5.{host}-{os.getpid()}.def456.tmp"
    other_host = tmp_path / f".ckpt_00000002.safetensors.elsewhere-{dead.pid}.ghi789.tmp"
    for f in (stale, live, other_host):
        f.write_bytes(b"partial")
    atomic_write_bytes(tmp_path / "metrics.json", b"{}")
    assert not stale.exists() and live.exists() and other_host.exists()
    assert (tmp_path / "metrics.json").read_bytes() == b"{}"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live.name, other_host.name, "metrics.json"])


def _forged(path, header: dict, body: bytes = b"", length: int | None = None):
    """A safetensors file with this JSON header (and, when given, a header length that lies)."""
    import json
    import struct

    raw = json.dumps(header).encode()
    path.write_bytes(struct.pack("<Q", len(raw) if length is None else length) + raw + body)
    return path


_F32x2 = {"dtype": "F32", "shape": [2], "data_offsets": [0, 8]}


@pytest.mark.parametrize("header,body,length,msg", [
    ({"w": _F32x2}, b"\0" * 8, 1 << 40, r"not a valid safetensors file \(SafetensorError: .*header too large"),
    ({"w": _F32x2}, b"\0" * 8, 10_000, r"not a valid safetensors file \(SafetensorError: .*invalid header length"),
    ({"w": _F32x2}, b"\0" * 4, None, r"not a valid safetensors file \(SafetensorError: .*not fully covered"),
    ({"w": {"dtype": "F32", "shape": [3], "data_offsets": [0, 8]}}, b"\0" * 8, None, "invalid shape, data type"),
    ({"w": {"dtype": "F99", "shape": [2], "data_offsets": [0, 8]}}, b"\0" * 8, None, "unknown variant `F99`"),
    ({"w": {"dtype": "F32", "shape": [1 << 62, 1 << 62], "data_offsets": [0, 8]}}, b"\0" * 8, None, "overflow"),
    ({"__metadata__": {"json": 5}, "w": _F32x2}, b"\0" * 8, None, "expected a string"),
    ({"__metadata__": {"json": "[" * 5000}, "w": _F32x2}, b"\0" * 8, None,
     r"metadata 'json' is JSON nested deeper than 64 levels"),
    ({"__metadata__": {"json": '{"a": ' + "9" * 5000 + "}"}, "w": _F32x2}, b"\0" * 8, None,
     r"metadata 'json' is not valid JSON \(Exceeds the limit"),
    ({"__metadata__": {"json": "{oops"}, "w": _F32x2}, b"\0" * 8, None, r"metadata 'json' is not valid JSON"),
])
def test_forged_safetensors_are_one_line_naming_the_file(tmp_path, header, body, length, msg):
    p = _forged(tmp_path / "f.safetensors", header, body, length)
    for read in (lambda: load_checkpoint(p), lambda: load_state_dict_file(p)):
        with pytest.raises(ToolkitError, match=r"f.safetensors: .*" + msg) as e:
            read()
        assert "\n" not in str(e.value)


def test_a_checkpoint_too_big_for_the_memory_budget_is_refused_before_reading(tmp_path, monkeypatch):
    save_checkpoint(tmp_path / "c.safetensors", {"w": torch.zeros(1000)})
    monkeypatch.setenv("DITGAZE_MEMORY_GB", str(1000 / (1 << 30)))
    with pytest.raises(ToolkitError, match=r"c.safetensors: reading its tensors would allocate"):
        load_checkpoint(tmp_path / "c.safetensors")
    from toolkit.io import load_metadata

    assert load_metadata(tmp_path / "c.safetensors") == {}  # the header alone is read whatever the budget
