import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from toolkit import ToolkitError
from train.training.checkpoint import CheckpointManager, load_training_checkpoint, save_training_checkpoint
from train.training.loop import MetricsLogger, TrainingDiverged, train_loop

ROOT = Path(__file__).resolve().parents[3]


def _problem(seed=0):
    torch.manual_seed(seed)
    model = torch.nn.Sequential(torch.nn.Linear(4, 16), torch.nn.Tanh(), torch.nn.Dropout(0.1), torch.nn.Linear(16, 1))
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    w = torch.tensor([1.0, -2.0, 0.5, 3.0])

    def step_fn(step, g):
        x = torch.randn(32, 4, generator=g)
        loss = ((model(x).squeeze(-1) - x @ w) ** 2).mean()
        return {"total": loss, "mse": loss}

    return model, opt, step_fn


def test_resume_reproduces_uninterrupted_run(tmp_path):
    m1, o1, f1 = _problem()
    train_loop("t", f1, modules={"m": m1}, optimizers={"o": o1}, steps=30, run_dir=tmp_path / "a",
               ckpt_every=10, progress=False)
    m2, o2, f2 = _problem()
    train_loop("t", f2, modules={"m": m2}, optimizers={"o": o2}, steps=20, run_dir=tmp_path / "b",
               ckpt_every=10, progress=False)
    # A fresh process state (different RNG, fresh model) resumes from the step-20 checkpoint.
    torch.manual_seed(123)
    m3, o3, f3 = _problem(seed=99)
    out = train_loop("t", f3, modules={"m": m3}, optimizers={"o": o3}, steps=30, run_dir=tmp_path / "b",
                     ckpt_every=10, resume=True, progress=False)
    assert out["step"] == 30
    for p, q in zip(m1.parameters(), m3.parameters()):
        assert torch.equal(p, q)


def test_lr_factor_sets_rates_and_survives_resume(tmp_path):
    """The rates follow ``lr_factor`` of the step, and a resumed run restores the entry rates (not the saved
    ones of the checkpoint's last step) before applying it: the same weights as the uninterrupted run."""
    factor = lambda step: 1.0 / (1 + step)  # noqa: E731
    m1, o1, f1 = _problem()
    seen = []
    train_loop("t", lambda s, g: (seen.append(o1.param_groups[0]["lr"]), f1(s, g))[1], modules={"m": m1},
               optimizers={"o": o1}, steps=30, run_dir=tmp_path / "a", ckpt_every=10, progress=False,
               lr_factor=factor)
    # Set before each update: the rate the step-s update used is read at step s + 1.
    assert seen[1:] == pytest.approx([1e-2 * factor(s) for s in range(29)])
    m2, o2, f2 = _problem()
    train_loop("t", f2, modules={"m": m2}, optimizers={"o": o2}, steps=20, run_dir=tmp_path / "b",
               ckpt_every=10, progress=False, lr_factor=factor)
    m3, o3, f3 = _problem(seed=99)
    train_loop("t", f3, modules={"m": m3}, optimizers={"o": o3}, steps=30, run_dir=tmp_path / "b",
               ckpt_every=10, resume=True, progress=False, lr_factor=factor)
    for p, q in zip(m1.parameters(), m3.parameters()):
        assert torch.equal(p, q)
    m4, o4, f4 = _problem()
    train_loop("t", f4, modules={"m": m4}, optimizers={"o": o4}, steps=30, run_dir=tmp_path / "c",
               ckpt_every=10, progress=False)
    assert not all(torch.equal(p, q) for p, q in zip(m1.parameters(), m4.parameters()))


def test_nan_loss_stops_with_step_terms_and_checkpoint(tmp_path):
    model, opt, f = _problem()

    def step_fn(step, g):
        terms = f(step, g)
        if step == 12:
            terms = {"total": terms["total"] * float("nan"), "mse": terms["mse"]}
        return terms

    with pytest.raises(TrainingDiverged, match=r"non-finite loss at step 12: total=nan.*last good checkpoint: .*ckpt_00000010"):
        train_loop("t", step_fn, modules={"m": model}, optimizers={"o": opt}, steps=20, run_dir=tmp_path,
                   ckpt_every=5, progress=False)


def test_metrics_jsonl(tmp_path):
    model, opt, f = _problem()
    ml = MetricsLogger(tmp_path, tensorboard=False)
    train_loop("t", f, modules={"m": model}, optimizers={"o": opt}, steps=10, run_dir=tmp_path, log_every=5,
               metrics=ml, progress=False)
    recs = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in recs] == [5, 10] and all("mse" in r and "grad_norm" in r for r in recs)


def test_a_resumed_stage_logs_each_step_once_and_drops_a_torn_line(tmp_path):
    model, opt, f = _problem()
    ml = MetricsLogger(tmp_path, tensorboard=False)
    train_loop("t", f, modules={"m": model}, optimizers={"o": opt}, steps=6, run_dir=tmp_path, log_every=1,
               ckpt_every=2, metrics=ml, progress=False)
    ml.log("other", 9, {"x": 1.0})  # another stage's record survives
    for p in CheckpointManager(tmp_path / "checkpoints").all():  # a "crash" after step 6, last checkpoint at 4
        if not p.name.endswith("04.safetensors"):
            p.unlink()
    with open(tmp_path / "metrics.jsonl", "a") as fh:
        fh.write('{"stage": "t", "st')  # torn mid-write
    model, opt, f = _problem()
    train_loop("t", f, modules={"m": model}, optimizers={"o": opt}, steps=8, run_dir=tmp_path, log_every=1,
               ckpt_every=2, metrics=ml, progress=False, resume=True)
    recs = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [(r["stage"], r["step"]) for r in recs] == [("t", s) for s in (1, 2, 3, 4)] + [("other", 9)] + [
        ("t", s) for s in (5, 6, 7, 8)]


@pytest.mark.parametrize("bad", [{"ckpt_every": 0}, {"log_every": 0}, {"grad_clip": -1.0}, {"grad_clip": float("nan")}])
def test_loop_settings_that_cannot_work_are_refused_before_a_step(tmp_path, bad):
    model, opt, f = _problem()
    before = [p.detach().clone() for p in model.parameters()]
    with pytest.raises(ToolkitError, match=f"t: .*{next(iter(bad))}"):
        train_loop("t", f, modules={"m": model}, optimizers={"o": opt}, steps=3, run_dir=tmp_path, progress=False,
                   **bad)
    assert all(torch.equal(a, b) for a, b in zip(before, model.parameters()))


def test_incompatible_and_corrupt_checkpoints(tmp_path):
    model, opt, _ = _problem()
    save_training_checkpoint(tmp_path / "c.safetensors", step=3, modules={"m": model}, optimizers={"o": opt})
    other = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Tanh(), torch.nn.Dropout(0.1), torch.nn.Linear(8, 1))
    with pytest.raises(ToolkitError, match="incompatible checkpoint for 'm'.*shape"):
        load_training_checkpoint(tmp_path / "c.safetensors", modules={"m": other})
    with pytest.raises(ToolkitError, match="no weights for module 'x'"):
        load_training_checkpoint(tmp_path / "c.safetensors", modules={"x": model})
    two_groups = torch.optim.Adam([{"params": [model[0].weight]}, {"params": [model[0].bias]}], lr=1e-2)
    with pytest.raises(ToolkitError, match=r"c\.safetensors: incompatible state for optimizer 'o'"):
        load_training_checkpoint(tmp_path / "c.safetensors", modules={"m": model}, optimizers={"o": two_groups})
    from toolkit.io import load_tensors, save_tensors

    tensors, meta = load_tensors(tmp_path / "c.safetensors")
    save_tensors(tmp_path / "norng.safetensors", tensors, {k: v for k, v in meta.items() if k != "rng"})
    with pytest.raises(ToolkitError, match=r"norng\.safetensors: has no random-number state .*'rng'"):
        load_training_checkpoint(tmp_path / "norng.safetensors", modules={"m": model})
    raw = (tmp_path / "c.safetensors").read_bytes()
    (tmp_path / "c.safetensors").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ToolkitError, match="not a valid safetensors"):
        load_training_checkpoint(tmp_path / "c.safetensors", modules={"m": model})


def test_manager_keeps_newest(tmp_path):
    model, opt, _ = _problem()
    mgr = CheckpointManager(tmp_path, keep=2)
    for s in (1, 2, 3):
        mgr.save(s, modules={"m": model}, optimizers={"o": opt})
    assert [p.name for p in mgr.all()] == ["ckpt_00000002.safetensors", "ckpt_00000003.safetensors"]
    # A newest checkpoint damaged after it was written: resume from the one before it.
    mgr.path_for(3).write_bytes(b"")
    assert mgr.newest()[0] == mgr.path_for(2)
    assert mgr.skipped == [mgr.path_for(3)]


_SCRIPT = textwrap.dedent(
    """
    import sys, time, torch
    sys.path.insert(0, {root!r})
    from tests.train.training.test_loop import _problem
    from train.training.loop import train_loop
    model, opt, f = _problem()
    seen = []
    def slow(step, g):
        if not seen:
            seen.append(step)
            print(f"first step {{step}}", flush=True)
        if step >= {slow_from}:
            time.sleep(0.2)
        return f(step, g)
    out = train_loop("t", slow, modules={{"m": model}}, optimizers={{"o": opt}}, steps=40, run_dir={run!r},
                     ckpt_every=5, resume=True, progress=False)
    torch.save([p.detach() for p in model.parameters()], {run!r} + "/final.pt")
    """
)


def _spawn(run, slow_from):
    code = _SCRIPT.format(root=str(ROOT), run=str(run), slow_from=slow_from)
    return subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def test_sigkill_then_resume_matches_uninterrupted(tmp_path):
    ref = _spawn(tmp_path / "ref", slow_from=10**9)
    assert ref.wait(timeout=120) == 0, ref.stderr.read().decode()
    proc = _spawn(tmp_path / "run", slow_from=12)
    mgr = CheckpointManager(tmp_path / "run" / "checkpoints")
    import time

    deadline = time.time() + 60
    while time.time() < deadline and not any(p.name.endswith("0015.safetensors") for p in mgr.all()):
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (tmp_path / "run" / "final.pt").exists()
    newest = mgr.all()[-1].name
    assert newest >= "ckpt_00000015.safetensors", newest  # killed mid-run, after the step-15 checkpoint
    done = _spawn(tmp_path / "run", slow_from=10**9)
    out, err = done.communicate(timeout=120)
    assert done.returncode == 0, err.decode()
    # It went on from the newest checkpoint, not from step 0 (a deterministic retrain would also match).
    assert f"first step {int(newest[5:13])}" in out.decode(), out.decode()
    a = torch.load(tmp_path / "ref" / "final.pt", weights_only=True)
    b = torch.load(tmp_path / "run" / "final.pt", weights_only=True)
    assert all(torch.equal(x, y) for x, y in zip(a, b))


def test_sigint_saves_checkpoint_and_exits_cleanly(tmp_path):
    proc = _spawn(tmp_path / "run", slow_from=3)
    mgr = CheckpointManager(tmp_path / "run" / "checkpoints")
    import time

    deadline = time.time() + 60
    while time.time() < deadline and not mgr.all():
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode != 0
    import re

    m = re.search(rb"interrupted at step (\d+); checkpoint saved to (\S+)", err)
    assert m, err.decode()[-500:]
    step, path = int(m.group(1)), Path(m.group(2).decode())
    assert path.exists() and path.name == f"ckpt_{step:08d}.safetensors"


def test_a_stop_on_any_rank_stops_every_rank_at_the_same_step(tmp_path, monkeypatch):
    """Under torchrun the stop flag is agreed by all ranks before each step (else one rank would leave for its
    checkpoint while the others wait in the step's gradient all-reduce). Simulated: the other rank's vote says
    stop before step 2; this rank's own flag never rose."""
    import train.training.loop as loop
    from train.training.distributed import DistInfo
    from train.training.loop import TrainingInterrupted

    votes = []

    def all_ranks(ok, info):
        votes.append(ok)
        return ok and len(votes) != 5  # per step: the stop vote, then the finite-loss vote; 5th: step 2's stop

    monkeypatch.setattr(loop, "all_ranks", all_ranks)
    monkeypatch.setattr(loop, "average_gradients", lambda params, info: None)
    model, opt, step_fn = _problem()
    with pytest.raises(TrainingInterrupted, match="step 2"):
        train_loop("s", step_fn, modules={"m": model}, optimizers={"o": opt}, steps=10, run_dir=tmp_path,
                   ckpt_every=100, progress=False, dist_info=DistInfo(rank=0, world_size=2))
    assert votes[4] is True  # this rank voted to go on
    assert CheckpointManager(tmp_path / "checkpoints").newest()[0].name[5:13] == "00000002"


def test_a_checkpoint_of_another_training_is_refused_and_a_fresh_run_clears_the_folder(tmp_path):
    """Checkpoints carry the training's fingerprint: --resume refuses one written under another, and a run that
    does not resume starts from an empty folder, so another run's later checkpoints can neither outnumber its
    own nor be resumed by mistake."""
    m1, o1, f1 = _problem()
    train_loop("t", f1, modules={"m": m1}, optimizers={"o": o1}, steps=30, run_dir=tmp_path, ckpt_every=10,
               progress=False, fingerprint="A")
    mgr = CheckpointManager(tmp_path / "checkpoints")
    assert [p.name for p in mgr.all()] == ["ckpt_00000020.safetensors", "ckpt_00000030.safetensors"]
    m2, o2, f2 = _problem()
    with pytest.raises(ToolkitError, match=r"ckpt_00000030.safetensors: written by a run under another config.*"
                                           r"rerun without --resume"):
        train_loop("t", f2, modules={"m": m2}, optimizers={"o": o2}, steps=40, run_dir=tmp_path, ckpt_every=10,
                   progress=False, fingerprint="B", resume=True)
    out = train_loop("t", f2, modules={"m": m2}, optimizers={"o": o2}, steps=20, run_dir=tmp_path, ckpt_every=10,
                     progress=False, fingerprint="B")
    assert [p.name for p in mgr.all()] == ["ckpt_00000010.safetensors", "ckpt_00000020.safetensors"]
    assert out["checkpoint"] == mgr.path_for(20)
    m3, o3, f3 = _problem()  # the same fingerprint resumes (training longer is the same training)
    assert train_loop("t", f3, modules={"m": m3}, optimizers={"o": o3}, steps=25, run_dir=tmp_path, ckpt_every=10,
                      progress=False, fingerprint="B", resume=True)["step"] == 25


def test_a_resume_past_a_damaged_checkpoint_says_so(tmp_path):
    m1, o1, f1 = _problem()
    train_loop("t", f1, modules={"m": m1}, optimizers={"o": o1}, steps=20, run_dir=tmp_path, ckpt_every=10,
               progress=False)
    newest = CheckpointManager(tmp_path / "checkpoints").path_for(20)
    newest.write_bytes(newest.read_bytes()[:100])
    lines = []
    m2, o2, f2 = _problem()
    train_loop("t", f2, modules={"m": m2}, optimizers={"o": o2}, steps=20, run_dir=tmp_path, ckpt_every=10,
               progress=False, resume=True, log=lines.append)
    assert lines == ["[t] skipped unreadable checkpoint(s) ['ckpt_00000020.safetensors']; resuming from "
                     "ckpt_00000010.safetensors"]


def test_a_stop_signal_during_the_last_step_stops_the_run(tmp_path):
    """Ctrl-C in the last step: its checkpoint is saved and the run stops, not going on to the next stage."""
    from train.training.loop import TrainingInterrupted

    model, opt, f = _problem()

    def step_fn(step, g):
        if step == 4:
            os.kill(os.getpid(), signal.SIGINT)  # the loop's handler sets its flag
        return f(step, g)

    with pytest.raises(TrainingInterrupted, match=r"interrupted at its last step \(5\); checkpoint saved to "
                                                  r".*ckpt_00000005.safetensors"):
        train_loop("t", step_fn, modules={"m": model}, optimizers={"o": opt}, steps=5, run_dir=tmp_path,
                   ckpt_every=100, progress=False)


def test_weights_gone_non_finite_inside_the_forward_pass_are_a_divergence(tmp_path):
    """A step that fails on non-finite weights (a rasterizer refusing NaN means, say) is reported as the
    training's divergence, with the step and the last good checkpoint, not as the forward pass's error."""
    model, opt, f = _problem()

    def step_fn(step, g):
        if step == 7:
            with torch.no_grad():
                model[0].weight[0, 0] = float("inf")
            raise ToolkitError("rasterize: means contains NaN or inf values")
        return f(step, g)

    with pytest.raises(TrainingDiverged, match=r"t: the weights are not finite at step 7 \(rasterize: .*\); last "
                                               r"good checkpoint: .*ckpt_00000005"):
        train_loop("t", step_fn, modules={"m": model}, optimizers={"o": opt}, steps=10, run_dir=tmp_path,
                   ckpt_every=5, progress=False)
    model2, opt2, f2 = _problem()

    def failing(step, g):  # finite weights: the step's own error stands
        raise ToolkitError("some input error")

    with pytest.raises(ToolkitError, match="^some input error$"):
        train_loop("t", failing, modules={"m": model2}, optimizers={"o": opt2}, steps=10, run_dir=tmp_path / "b",
                   progress=False)
