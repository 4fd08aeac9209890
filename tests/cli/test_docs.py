"""The README and docs/ against the code: every `photoreal …` command the guides show parses with today's CLI,
every relative link resolves (file and heading), and every docs file a comment points at exists.

Oracle: the CLI's own argparse parser (nothing is run) and the repository's files. A flag renamed or dropped, a
docs file moved, or a heading renamed under a link fails here instead of in a reader's shell."""

from __future__ import annotations

import argparse
import re
import shlex
from pathlib import Path

import pytest

from photoreal.cli import build_parser

ROOT = Path(__file__).resolve().parents[2]
MARKDOWN = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), ROOT / "scenes" / "assets" / "README.md"]


def readme_commands(text: str) -> list[tuple[int, str]]:
    """(line number, command) for each ``photoreal …`` line of the README's ``sh`` blocks: continuations joined,
    comments dropped."""
    out, in_sh, pending, start = [], False, "", 0
    for n, line in enumerate(text.splitlines(), 1):
        if line.startswith("```"):
            in_sh = line.strip() == "```sh" and not in_sh
            continue
        if not in_sh:
            continue
        code = line.split(" #", 1)[0].rstrip() if not line.lstrip().startswith("#") else ""
        if pending:
            pending += " " + code.strip()
        elif code.startswith("photoreal "):
            pending, start = code, n
        if pending and not pending.endswith("\\"):
            out.append((start, pending))
            pending = ""
        elif pending:
            pending = pending[:-1].rstrip()
    return out


def _subparser(parser: argparse.ArgumentParser, words: list[str]) -> tuple[argparse.ArgumentParser, list[str]]:
    """The (sub)parser that ``words`` lead to, and the words left for it."""
    while words:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs or words[0] not in subs[0].choices:
            break
        parser, words = subs[0].choices[words[0]], words[1:]
    return parser, words


def test_the_readme_starts_with_make_demo_and_make_test_and_ci_runs_make_test():
    head = (ROOT / "README.md").read_text().splitlines()[:8]
    block = [ln.split("#")[0].strip() for ln in head[head.index("```sh") + 1:head.index("```", head.index("```sh") + 1)]]
    assert [b for b in block if b] == ["make demo", "make test"], block
    assert "make test" in (ROOT / ".ci" / "run").read_text()


def test_readme_command_finder_joins_continuations_and_drops_comments():
    text = "```sh\nphotoreal a --x 1 \\\n    --y 2   # note\n# with a GPU: skip\nmake demo\n```\nphotoreal b\n"
    assert readme_commands(text) == [(2, "photoreal a --x 1 --y 2")]


#: the guides: the README and docs/*.md (docs/results/ records commands as they were run, flags since renamed too)
GUIDES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
COMMANDS = [(f"{md.relative_to(ROOT)}:{n}", c) for md in GUIDES for n, c in readme_commands(md.read_text())]


def test_the_guides_show_commands():
    assert len(COMMANDS) >= 40, len(COMMANDS)  # the finder still sees the guides' blocks
    assert len(readme_commands((ROOT / "README.md").read_text())) >= 8  # the README's first runs


@pytest.mark.parametrize("line,command", COMMANDS, ids=[n for n, _ in COMMANDS])
def test_every_guide_command_parses(line, command):
    """Options in ``[…]`` are optional: their flags must exist on that command; the rest must parse as written."""
    parser = build_parser()
    optional = re.findall(r"\[([^\]]*)\]", command)
    words = shlex.split(re.sub(r"\[[^\]]*\]", " ", command))[1:]
    try:
        parser.parse_args(words)
    except SystemExit as exc:
        pytest.fail(f"{line}: `{command}` does not parse (exit {exc.code})")
    sub, _ = _subparser(parser, words)
    known = {s for a in sub._actions for s in a.option_strings}
    for group in optional:
        for flag in re.findall(r"(?<![\w-])--?[a-zA-Z][\w-]*", group):
            assert flag in known, f"{line}: {flag} is not an option of `{sub.prog}`"


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    s = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return s.replace(" ", "-")


LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


@pytest.mark.parametrize("md", MARKDOWN, ids=[str(p.relative_to(ROOT)) for p in MARKDOWN])
def test_relative_links_resolve(md):
    bad = []
    for target in LINK.findall(md.read_text()):
        if re.match(r"[a-z]+:", target):
            continue  # http:, https:, mailto:
        path, _, anchor = target.partition("#")
        dest = (md.parent / path).resolve() if path else md
        if not dest.exists():
            bad.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md":
            slugs = {_slug(h) for h in re.findall(r"^#+ (.*)$", dest.read_text(), re.M)}
            if anchor not in slugs:
                bad.append(f"{target}: no heading with that anchor")
    assert not bad, f"{md.relative_to(ROOT)}: " + "; ".join(bad)


def test_docs_files_named_in_code_exist():
    named = set()
    for py in ROOT.glob("*/**/*.py"):
        if ".venv" in py.parts:
            continue
        named |= {(py, m) for m in re.findall(r"docs/[\w/-]+\.md", py.read_text())}
    assert named, "no code names a docs file (the pattern is stale)"
    missing = sorted(f"{py.relative_to(ROOT)}: {m}" for py, m in named if not (ROOT / m).is_file())
    assert not missing, missing
