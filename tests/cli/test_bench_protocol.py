"""One benchmark protocol: a new benchmark is its own module plus one registry line, and the CLI, `bench all` and
the demo's table pick it up. Oracle: a tiny benchmark written here, whose result is a closed form of its settings."""

from __future__ import annotations

import json
import sys
import textwrap

import pytest

from photoreal import benchmarks
from photoreal.benchmarks import REGISTRY, Entry
from photoreal.cli import main

TINY = textwrap.dedent('''
    from dataclasses import dataclass, asdict

    @dataclass
    class TinySettings:
        count: int = 4  #: how many squares to add up
        scale: float = 0.5  #: each square times this

    SETTINGS = TinySettings
    SUMMARY = ("total",)

    def run(s, work, pool, show_progress):
        work.mkdir(parents=True, exist_ok=True)
        (work / "partial.txt").write_text(str(s.count))
        return {"total": s.scale * sum(k * k for k in range(s.count)), "settings": asdict(s)}
''')


@pytest.fixture
def tiny(tmp_path, monkeypatch):
    (tmp_path / "mods").mkdir()
    (tmp_path / "mods" / "tiny_bench.py").write_text(TINY)
    monkeypatch.syspath_prepend(str(tmp_path / "mods"))
    monkeypatch.setitem(REGISTRY, "tiny", Entry("tiny_bench", "a tiny benchmark"))
    yield tmp_path
    sys.modules.pop("tiny_bench", None)


def test_a_registered_module_is_a_benchmark_with_flags_from_its_settings(tiny, capsys):
    out = tiny / "out" / "tiny.json"
    assert main(["bench", "tiny", "--json", str(out), "--count", "3", "--scale", "2"]) == 0
    assert json.loads(capsys.readouterr().out) == {"total": 2.0 * (0 + 1 + 4)}
    assert json.loads(out.read_text())["total"] == 10.0
    assert (tiny / "out" / "tiny_work" / "partial.txt").read_text() == "3"  # kept: a rerun re-reads it
    assert main(["bench", "tiny", "--json", str(out), "--clean"]) == 0
    assert json.loads(out.read_text())["total"] == 0.5 * 14 and not (tiny / "out" / "tiny_work").exists()
    assert main(["bench", "tiny", "--help"]) == 0
    text = capsys.readouterr().out
    assert "--count COUNT" in text and "how many squares to add up (default: 4)" in text and "--clean" in text


def test_bench_all_and_the_demo_table_loop_over_the_registry(tiny, capsys, monkeypatch):
    from photoreal.demo import demo_benchmarks

    assert main(["bench", "all", "--out-dir", str(tiny / "b"), "--only", "tiny"]) == 0
    assert json.loads((tiny / "b" / "tiny.json").read_text())["total"] == 7.0
    assert main(["bench", "all", "--out-dir", str(tiny / "b"), "--only", "nonsense"]) == 2
    assert "--only nonsense: not a benchmark" in capsys.readouterr().err
    found = demo_benchmarks(tiny / "demo", tiny / "b")
    assert found == {"tiny": ["total"]}
    page = (tiny / "demo" / "sections" / "90_benchmarks.html").read_text()
    assert "photoreal bench tiny" in page and "&quot;total&quot;: 7.0" in page and "Not run yet: plugins" in page


def test_every_registered_benchmark_follows_the_protocol():
    """Each module defines what the runner calls (imports only: nothing runs)."""
    for name in REGISTRY:
        mod = benchmarks.load(name)
        assert hasattr(mod, "SETTINGS") and callable(mod.run), name
        assert hasattr(mod, "summary") or hasattr(mod, "SUMMARY"), name
        mod.SETTINGS()  # every setting has a default
    assert benchmarks.json_name("face-learned") == "face_learned.json"
