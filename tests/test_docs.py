"""What the documentation promises still holds: every ``acinoset <command> [<subcommand>]`` that
README.md and docs/*.md show (in code, fenced or inline) is a command of the ``acinoset`` script
whose ``--help`` exits 0, run as a user runs it (a separate process); every ``bench/*.py`` they name
exists; and README.md stays a front page of at most 150 lines.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
README_MAX_LINES = 150

CODE = re.compile(r"```.*?```|`[^`\n]+`", re.S)  # fenced blocks, then inline code spans
# "acinoset WORD [WORD|WORD]" not inside a longer name (acinoset[export], ACINOSET_..., acinoset.egg-info)
COMMAND = re.compile(r"(?<![\w\[-])acinoset[ \t]+([a-z][a-z-]*)(?:[ \t]+([a-z][a-z|-]*))?")
BENCH = re.compile(r"\bbench/[\w./-]+\.py\b")


def _code(path: Path) -> str:
    return "\n".join(CODE.findall(path.read_text(encoding="utf-8")))


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def named_commands(paths: list[Path]) -> dict[tuple[str, ...], set[str]]:
    """Each command line the docs name, as the words before its options: ``("solve",)``,
    ``("evaluate", "loco")``; with the files naming it. A second word counts as a subcommand when the
    command has subcommands (``status|stop`` names two); otherwise it is the command's argument."""
    from graph.app.cli import build_parser
    from service.cli import COMMANDS

    commands = _subcommands(build_parser(COMMANDS))
    named: dict[tuple[str, ...], set[str]] = {}
    for path in paths:
        for command, second in COMMAND.findall(_code(path)):
            words: list[tuple[str, ...]] = [(command,)]
            subs = _subcommands(commands[command]) if command in commands else {}
            if subs and second:
                words = [(command, s) for s in second.split("|") if s]
            for w in words:
                named.setdefault(w, set()).add(path.name)
    return named


NAMED = named_commands(DOCS)


def test_readme_is_a_front_page():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; the reference belongs in docs/"


def test_the_docs_name_the_commands_a_user_starts_with():
    readme = named_commands([ROOT / "README.md"])
    assert {("serve",), ("demo",), ("solve",), ("evaluate", "loco")} <= set(readme), sorted(readme)
    every = {w[0] for w in NAMED}
    assert {"solve", "plot", "evaluate", "simulate", "demo", "anipose", "export", "video", "calibrate", "resident",
            "serve", "worker", "users", "jobs"} <= every, sorted(every)


@pytest.mark.parametrize("words", sorted(NAMED), ids=" ".join)
def test_every_command_the_docs_name_runs(words):
    """``--help`` of the command (and subcommand) exits 0 through the installed entry point's module;
    a name that is no command (a typo, a command removed) fails with the files that name it."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               ACINOSET_RESIDENT="0")
    proc = subprocess.run([sys.executable, "-m", "service.cli", *words, "--help"], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=120)
    where = ", ".join(sorted(NAMED[words]))
    assert proc.returncode == 0, f"'acinoset {' '.join(words)}' (named in {where}): {proc.stderr.strip()}"
    assert proc.stdout.startswith(f"usage: acinoset {' '.join(words)}"), proc.stdout[:200]


def test_every_bench_script_the_docs_name_exists():
    named = {m: path.name for path in DOCS for m in BENCH.findall(path.read_text(encoding="utf-8"))}
    assert "bench/bench_fly_loco.py" in named, sorted(named)
    missing = sorted(f"{m} (in {where})" for m, where in named.items() if not (ROOT / m).is_file())
    assert not missing, missing
