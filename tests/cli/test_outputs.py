"""The one output rule (foundation.files.OutputPath) on every subcommand: each output flag goes through it, so a new
command cannot write outside it; a folder of the user's is refused by every command, before any work."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from foundation.files import FILE, FOLDER, RECORD, OutputPath, check_command_folder, claim_output_folder
from foundation.files import release_output_folder
from foundation.errors import UsageError
from photoreal.cli import build_parser

#: flags that name what a command writes (the issue's four, and the others of that kind)
OUTPUT_FLAGS = {"--out", "-o", "--output", "--json", "--out-dir", "--maps", "--checkpoint"}


def _subcommands() -> list[tuple[list[str], argparse.ArgumentParser]]:
    out = []

    def walk(p: argparse.ArgumentParser, words: list[str]) -> None:
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            out.append((words, p))
        for a in subs:
            for name, sp in a.choices.items():
                walk(sp, [*words, name])

    walk(build_parser(), [])
    return out


SUBCOMMANDS = _subcommands()
OUTPUTS = [(words, act) for words, p in SUBCOMMANDS for act in p._actions
           if set(act.option_strings) & OUTPUT_FLAGS]


def test_every_output_flag_of_every_subcommand_goes_through_the_rule():
    assert len(SUBCOMMANDS) > 30 and len(OUTPUTS) > 40  # the walk found the commands (not a vacuous pass)
    wrong = [f"{' '.join(words)} {act.option_strings[-1]}" for words, act in OUTPUTS
             if not isinstance(act.type, OutputPath) or act.type.command != " ".join(words)]
    assert not wrong, f"output flags outside foundation.files.OutputPath (use cli.common.out_opt): {wrong}"
    # and an option named like an output elsewhere is one too
    dests = [f"{' '.join(w)} {a.dest}" for w, p in SUBCOMMANDS for a in p._actions
             if a.dest in ("out", "out_dir", "json", "output") and not isinstance(a.type, OutputPath)]
    assert not dests


def _argv(words: list[str], parser: argparse.ArgumentParser, act: argparse.Action, value: str) -> list[str]:
    """The subcommand with placeholders for its required arguments and ``value`` for ``act``."""
    argv = list(words)
    for a in parser._actions:
        if a is act or isinstance(a, argparse._HelpAction):
            continue
        if not a.option_strings:
            argv.append(str(a.choices[0]) if a.choices else "placeholder")
        elif a.required:
            argv += [a.option_strings[-1], str(a.choices[0]) if a.choices else "placeholder"]
    return [*argv, act.option_strings[-1], value]


@pytest.mark.parametrize("words,act", OUTPUTS, ids=[f"{' '.join(w)} {a.option_strings[-1]}" for w, a in OUTPUTS])
def test_a_users_folder_or_file_is_refused_while_parsing(words, act, tmp_path, capsys):
    parsers = dict((" ".join(w), p) for w, p in SUBCOMMANDS)
    user = tmp_path / "thesis"
    user.mkdir()
    (user / "metrics.json").write_text("the user's")
    (user / "errors.json").write_text("the user's")
    flag = act.option_strings[-1]
    with pytest.raises(SystemExit) as exc:
        build_parser(words[0], words[1] if len(words) > 1 else None).parse_args(
            _argv(words, parsers[" ".join(words)], act, str(user)))  # a folder where a file goes: refused too
    err = capsys.readouterr().err
    assert exc.value.code == 2 and f"argument {'/'.join(act.option_strings)}: {user}" in err, err
    assert ("holds files" in err) if act.type.kind == FOLDER else ("is a folder, expected a file path" in err)
    assert sorted(p.name for p in user.iterdir()) == ["errors.json", "metrics.json"], flag


def test_a_folder_is_the_commands_own_by_its_record(tmp_path):
    p = tmp_path / "a" / "b"
    made = claim_output_folder(p, "morph run")
    assert made == tmp_path / "a" and json.loads((p / RECORD).read_text()) == {"command": "morph run"}
    (p / "checkpoint.npz").write_bytes(b"run")
    assert check_command_folder(p, "morph run") == p  # its own previous output: resumed
    with pytest.raises(UsageError, match=r"holds the output of `photoreal morph run`, not of `photoreal gan train`"):
        check_command_folder(p, "gan train")
    release_output_folder(p, made)  # not a failed start: it holds a checkpoint
    assert (p / "checkpoint.npz").is_file()
    (p / "checkpoint.npz").unlink()
    release_output_folder(p, made)  # nothing but the record: as it was before the claim
    assert not (tmp_path / "a").exists()
    q = tmp_path / "empty"
    q.mkdir()
    release_output_folder(q, claim_output_folder(q, "render"))
    assert q.is_dir() and not any(q.iterdir())  # a folder the user had stays, empty as it was
    (q / "notes.txt").write_text("mine")
    with pytest.raises(UsageError, match=r"holds files `photoreal render` did not write \(notes.txt\)"):
        check_command_folder(q, "render")


def test_output_kinds_are_checked():
    with pytest.raises(ValueError, match="kind 'dir'"):
        OutputPath("dir", "render")
    assert OutputPath(FILE, "render")("x.exr") == "x.exr"
    with pytest.raises(argparse.ArgumentTypeError, match="is a folder"):
        OutputPath(FILE, "render")(str(Path(__file__).parent))


def test_a_report_written_before_records_is_still_the_demos_but_a_users_page_is_not(tmp_path, capsys):
    old = tmp_path / "old"
    (old / "sections").mkdir(parents=True)
    (old / "index.html").write_text("<html>")
    (old / "demo.json").write_text("{}")
    assert build_parser("demo").parse_args(["demo", "--out", str(old)]).out == str(old)
    site = tmp_path / "site"
    site.mkdir()
    (site / "index.html").write_text("<html>my page</html>")
    with pytest.raises(SystemExit):
        build_parser("demo").parse_args(["demo", "--out", str(site)])
    assert "holds files `photoreal demo` did not write (index.html)" in capsys.readouterr().err
