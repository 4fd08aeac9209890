"""The foundation layer: the training loop's budgets, resume and NaN policy; checkpoint trees; optimiser state;
atomic writes and output checks; typed records."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import torch

import drjit as dr
import mitsuba as mi

from foundation.checkpoint import load_tree, save_tree
from foundation.errors import CheckpointError, NonFiniteError, UsageError
from foundation.files import atomic_dir, atomic_path, check_output_dir, read_json, write_json
from foundation.loop import LoopSettings, RunState, Stage, StepResult, rng_state, run_loop, set_rng_state
from foundation.optim_state import load_optimizer_state, optimizer_state
from foundation.records import from_json, to_json


class Quadratic(Stage):
    """Minimise ‖x − target‖² with Dr.Jit Adam on batches of random coordinates (needs RNG + moments to resume)."""

    name = "quadratic"

    def __init__(self, n: int = 32, lr: float = 0.05, seed: int = 0, poison: set[int] | None = None):
        self.rng = np.random.default_rng(seed)
        self.target = np.linspace(-1, 1, n).astype(np.float32)
        self.opt = mi.ad.Adam(lr=lr)
        self.opt["x"] = mi.Float(np.zeros(n, np.float32))
        self.poison = poison or set()
        self.applied: list[int] = []

    def fingerprint(self) -> dict:
        return {"n": len(self.target), "lr": self.opt.lr}

    def state(self) -> dict:
        return {"opt": optimizer_state(self.opt), "rng": rng_state(self.rng)}

    def load_state(self, tree: dict) -> None:
        load_optimizer_state(self.opt, tree["opt"])
        set_rng_state(self.rng, tree["rng"])

    def step(self, it: int) -> StepResult:
        idx = self.rng.choice(len(self.target), 8, replace=False)
        x = self.opt["x"]
        w = np.zeros(len(self.target), np.float32)
        w[idx] = 1.0
        loss = dr.sum(mi.Float(w) * dr.square(x - mi.Float(self.target)))
        if it in self.poison:
            loss = loss * mi.Float(float("nan"))
        dr.backward(loss)
        value = float(loss.array[0])
        return StepResult(value, math.isfinite(value), log={"half": value / 2})

    def apply(self, it: int) -> None:
        self.opt.step()
        self.applied.append(it)

    def discard(self, it: int) -> None:
        dr.set_grad(self.opt["x"], 0)

    def finish(self, run: RunState):
        return {"x": np.array(self.opt["x"]), "training": run.summary()}


def test_loop_converges_and_writes_metrics(tmp_path):
    r = run_loop(Quadratic(), LoopSettings(steps=300), metrics_path=tmp_path / "m.json", show_progress=False)
    np.testing.assert_allclose(r["x"], np.linspace(-1, 1, 32), atol=0.05)  # closed form: x = target
    saved = json.loads((tmp_path / "m.json").read_text())
    assert saved["training"]["steps"] == 300 and saved["training"]["skipped_steps"] == 0
    assert saved["training"]["loss_last"] < 1e-2 * saved["training"]["loss_first"]


def test_interrupted_and_resumed_equals_uninterrupted_bit_for_bit(tmp_path):
    full = run_loop(Quadratic(), LoopSettings(steps=40, checkpoint_every=7), tmp_path / "a.npz", show_progress=False)
    assert run_loop(Quadratic(), LoopSettings(steps=40, checkpoint_every=7), tmp_path / "b.npz", budget_steps=13,
                    show_progress=False) is None
    assert run_loop(Quadratic(), LoopSettings(steps=40, checkpoint_every=7), tmp_path / "b.npz", budget_steps=5,
                    show_progress=False) is None
    resumed = run_loop(Quadratic(), LoopSettings(steps=40, checkpoint_every=7), tmp_path / "b.npz",
                       show_progress=False)
    np.testing.assert_array_equal(resumed["x"], full["x"])
    a, b = resumed["training"], full["training"]
    assert (a.steps, a.skipped_steps, a.loss_first, a.loss_last) == (b.steps, b.skipped_steps, b.loss_first, b.loss_last)
    # a finished run called again trains nothing and gives the same result
    again_stage = Quadratic()
    again = run_loop(again_stage, LoopSettings(steps=40), tmp_path / "b.npz", show_progress=False)
    np.testing.assert_array_equal(again["x"], full["x"])
    assert not again_stage.applied


def test_resume_without_the_saved_moments_would_differ(tmp_path):
    """The check above can fail: dropping Adam's moments (what reading a changed tuple layout loses) changes x."""
    run_loop(Quadratic(), LoopSettings(steps=20), tmp_path / "c.npz", budget_steps=10, show_progress=False)
    stage = Quadratic()
    tree = load_tree(tmp_path / "c.npz")
    stage.load_state(tree["stage"])
    stage.opt.reset("x")
    full = run_loop(Quadratic(), LoopSettings(steps=20), show_progress=False)
    run = RunState.from_tree(tree["loop"])
    for it in range(run.step, 20):
        stage.step(it)
        stage.apply(it)
    assert not np.array_equal(np.array(stage.opt["x"]), full["x"])


def test_nan_steps_are_skipped_counted_and_stop_after_k_in_a_row(tmp_path):
    s = Quadratic(poison={3, 4, 9})
    r = run_loop(s, LoopSettings(steps=20, max_nonfinite=3), show_progress=False)
    assert r["training"].skipped_steps == 3 and 3 not in s.applied and 9 not in s.applied and len(s.applied) == 17
    assert np.isfinite(r["x"]).all()
    with pytest.raises(NonFiniteError, match=r"quadratic: 3 steps in a row gave NaN/Inf .*\(steps 5–7\)"):
        run_loop(Quadratic(poison={5, 6, 7}), LoopSettings(steps=20, max_nonfinite=3), tmp_path / "n.npz",
                 show_progress=False)


def test_time_budget_ends_the_run(monkeypatch):
    clock = iter(np.arange(0, 1000, 0.5))
    monkeypatch.setattr("foundation.loop.time.perf_counter", lambda: float(next(clock)))
    r = run_loop(Quadratic(), LoopSettings(steps=1000, max_seconds=2.0), show_progress=False)
    assert r["training"].steps == 4 and r["training"].train_seconds == pytest.approx(2.0)  # 0.5 s per step


def test_other_settings_and_other_stages_are_refused_by_name(tmp_path):
    run_loop(Quadratic(), LoopSettings(steps=3), tmp_path / "q.npz", show_progress=False)
    with pytest.raises(CheckpointError, match=r"other settings or data \(lr: 0.05 → 0.1\)"):
        run_loop(Quadratic(lr=0.1), LoopSettings(steps=3), tmp_path / "q.npz", show_progress=False)

    class Other(Quadratic):
        pass

    with pytest.raises(CheckpointError, match="checkpoint of a Quadratic run, not of a Other run"):
        run_loop(Other(), LoopSettings(steps=3), tmp_path / "q.npz", show_progress=False)
    with pytest.raises(UsageError, match="steps must be an integer ≥ 0"):
        LoopSettings(steps=-1)
    with pytest.raises(UsageError, match="max_seconds must be > 0"):
        LoopSettings(steps=1, max_seconds=float("nan"))


# -- checkpoint trees and optimiser state -------------------------------------------------------------------------


def test_checkpoint_tree_round_trip_keeps_types(tmp_path):
    tree = {"a": np.arange(5, dtype=np.int16), 3: (1.5, None, True, "s"), "t": torch.tensor([1.0, 2.0]),
            "big": 2**100, "nested": [{"x": np.float32(2.5)}]}
    save_tree(tmp_path / "t.npz", tree)
    back = load_tree(tmp_path / "t.npz")
    assert back["a"].dtype == np.int16 and back["a"].tolist() == [0, 1, 2, 3, 4]
    assert back[3] == (1.5, None, True, "s") and isinstance(back[3], tuple)
    assert torch.equal(back["t"], tree["t"]) and back["big"] == 2**100 and back["nested"] == [{"x": 2.5}]
    with pytest.raises(TypeError, match="cannot store a object"):
        save_tree(tmp_path / "u.npz", {"o": object()})
    assert not (tmp_path / "u.npz").exists()


def test_optimizer_state_round_trip_drjit_and_torch():
    opt = mi.ad.Adam(lr=0.1)
    opt["t"] = mi.TensorXf(np.ones((2, 3), np.float32))
    opt["v"] = mi.Vector3f(1, 2, 3)
    opt.set_learning_rate({"v": 0.01})
    for _ in range(3):
        dr.backward(dr.sum(opt["t"].array * 2.0) + dr.sum(opt["v"].x * opt["v"].y))
        opt.step()
    saved = optimizer_state(opt)
    fresh = mi.ad.Adam(lr=0.1)
    fresh["t"] = mi.TensorXf(np.ones((2, 3), np.float32))
    fresh["v"] = mi.Vector3f(1, 2, 3)
    load_optimizer_state(fresh, saved)
    for o in (opt, fresh):  # one more step from both: identical
        dr.backward(dr.sum(o["t"].array * 2.0) + dr.sum(o["v"].x * o["v"].y))
        o.step()
    np.testing.assert_array_equal(np.array(fresh["t"]), np.array(opt["t"]))
    np.testing.assert_array_equal(np.array(fresh["v"]), np.array(opt["v"]))
    bad = mi.ad.Adam(lr=0.1)
    bad["t"] = mi.TensorXf(np.ones((3, 3), np.float32))
    bad["v"] = mi.Vector3f(1, 2, 3)
    with pytest.raises(CheckpointError, match="optimizer\\['t'\\]\\[0\\]: shape"):
        load_optimizer_state(bad, saved)

    p = torch.nn.Parameter(torch.ones(4))
    topt = torch.optim.Adam([p], lr=0.1)
    p.sum().backward()
    topt.step()
    st = optimizer_state(topt)
    q = torch.nn.Parameter(p.detach().clone())
    topt2 = torch.optim.Adam([q], lr=0.1)
    load_optimizer_state(topt2, st)
    assert torch.equal(topt2.state_dict()["state"][0]["exp_avg"], topt.state_dict()["state"][0]["exp_avg"])


# -- files and records --------------------------------------------------------------------------------------------


def test_atomic_writes_leave_nothing_on_error_and_folders_only_replace_their_own(tmp_path):
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "f.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash")
    assert list(tmp_path.iterdir()) == []
    with atomic_dir(tmp_path / "out", marker="done.json") as d:
        (d / "a.txt").write_text("1")
        (d / "done.json").write_text("{}")
    with atomic_dir(tmp_path / "out", marker="done.json") as d:  # a previous output: replaced
        (d / "b.txt").write_text("2")
        (d / "done.json").write_text("{}")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [".photoreal-manifest.json", "b.txt", "done.json"]
    (tmp_path / "out" / "notes.txt").write_text("mine")  # something the command did not write: never replaced
    with pytest.raises(UsageError, match=r"also holds what this command did not write \(notes.txt\)"):
        with atomic_dir(tmp_path / "out", marker="done.json"):
            pass
    assert (tmp_path / "out" / "notes.txt").read_text() == "mine"
    # a cache a later run derived from the folder (a pattern the command names) goes with it; a user's file does not
    (tmp_path / "out" / "notes.txt").unlink()
    (tmp_path / "out" / "cache_1.ply").write_text("derived")
    with pytest.raises(UsageError, match=r"did not write \(cache_1.ply\)"):
        check_output_dir(tmp_path / "out", "done.json", replace=True)
    with atomic_dir(tmp_path / "out", marker="done.json", derived=("cache_*.ply",)) as d:
        (d / "done.json").write_text("{}")
    assert not (tmp_path / "out" / "cache_1.ply").exists()
    (tmp_path / "out" / "cache_1.ply.txt").write_text("mine")
    with pytest.raises(UsageError, match=r"did not write \(cache_1.ply.txt\)"):
        check_output_dir(tmp_path / "out", "done.json", replace=True, derived=("cache_*.ply",))
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    with pytest.raises(UsageError, match="folder exists and is not empty .*no done.json"):
        check_output_dir(tmp_path / "mine", "done.json")
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"


def test_read_json_names_the_file(tmp_path):
    p = tmp_path / "x.json"
    for text, msg in (("", "empty file"), ("[1]", "expected a JSON object"), ("{\n'a'", "not valid JSON \\(line 2")):
        p.write_text(text)
        with pytest.raises(UsageError, match=f"x.json: {msg}"):
            read_json(p)
    write_json(p, {"a": np.float32(1.5), "b": Path("q")})
    assert read_json(p) == {"a": 1.5, "b": "q"}


@dataclass
class Inner:
    xy: tuple[float, float]


@dataclass
class Outer:
    name: str
    items: list[Inner]
    maybe: float | None = None
    tags: dict[str, int] = field(default_factory=dict)


def test_records_round_trip_and_name_the_bad_field():
    o = Outer("a", [Inner((1.0, 2.0))], None, {"k": 3})
    assert from_json(Outer, json.loads(json.dumps(to_json(o))), "f.json") == o
    with pytest.raises(UsageError, match="f.json: missing field 'items'"):
        from_json(Outer, {"name": "a"}, "f.json")
    with pytest.raises(UsageError, match=r"f.json: items\[0\].xy: expected 2 values, got 3"):
        from_json(Outer, {"name": "a", "items": [{"xy": [1, 2, 3]}]}, "f.json")
    with pytest.raises(UsageError, match="f.json: unknown field\\(s\\) extra"):
        from_json(Outer, {"name": "a", "items": [], "extra": 1}, "f.json")
