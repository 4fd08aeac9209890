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
