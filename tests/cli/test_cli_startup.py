"""Start-up: help and argument errors answer without importing what the command does not run.

Oracle: ``sys.modules`` of a fresh interpreter after the command (no timing: these machines are noisy; the
seconds are measured by ``photoreal bench startup``)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

PROBE = """
import json, sys
from photoreal.cli import main
try:
    code = main(sys.argv[1:])
except SystemExit as exc:
    code = exc.code
heavy = ("torch", "diffusers", "mitsuba", "drjit", "ray", "matplotlib", "scipy")
print(json.dumps({"code": code, "loaded": [m for m in heavy if m in sys.modules]}))
"""


def _loaded(*argv: str) -> dict:
    r = subprocess.run([sys.executable, "-c", PROBE, *argv], capture_output=True, text=True, timeout=120)
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_top_level_help_imports_none_of_the_libraries():
    r = _loaded("--help")
    assert r == {"code": 0, "loaded": []}, r


def test_an_unknown_command_is_a_usage_error_without_the_libraries():
    r = _loaded("no-such-command")
    assert r == {"code": 2, "loaded": []}, r


@pytest.mark.parametrize("argv", [("render", "--help"), ("morph", "run", "--help"), ("demo", "--help"),
                                  ("capture", "sfm", "--help"), ("capture", "import", "--help"),
                                  ("render",), ("morph", "run", "--iterations", "many")])
def test_render_morph_capture_and_demo_help_and_errors_never_import_torch(argv):
    """`render`, `morph`, `capture` and `demo` options come from settings of modules that torch stays out of (the
    GCN variant loads it on first use); an argument error exits 2 the same way."""
    r = _loaded(*argv)
    assert r["code"] == (0 if argv[-1] == "--help" else 2) and "torch" not in r["loaded"], r
    assert "diffusers" not in r["loaded"], r


EVERY_HELP = """
import contextlib, io, json, sys
from photoreal.benchmarks.startup import commands
from photoreal.cli import main
heavy = ("torch", "diffusers")
out = {"codes": {}, "first_heavy": None}
for name, argv in commands().items():
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            out["codes"][name] = main(argv)
        except SystemExit as exc:
            out["codes"][name] = exc.code
    loaded = [m for m in heavy if m in sys.modules]
    if loaded and out["first_heavy"] is None:
        out["first_heavy"] = [name, loaded]
print(json.dumps(out))
"""


def test_every_help_and_usage_error_answers_without_torch():
    """Every command line `photoreal bench startup` times (each group's and each subcommand's help, the usage
    errors), one after the other in one interpreter: all answer (exit 0, 2 for the errors) and none loads torch or
    diffusers, so none waits for them (the settings of torch models live in torch-free modules,
    :mod:`foundation.lazy`)."""
    r = subprocess.run([sys.executable, "-c", EVERY_HELP], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    bad = {n: c for n, c in out["codes"].items() if c != (2 if "usage error" in n else 0)}
    assert not bad, bad
    assert len(out["codes"]) >= 40 and out["first_heavy"] is None, out["first_heavy"]
