"""The commands the docs give (README.md, docs/*.md, models/README.md) exist as written: every ``python
bench/NAME.py ...`` names a script that runs (``--help``) and takes each long option the docs pass it, and every
``fms SUB ...`` a subcommand that takes each of its options. A renamed option or script otherwise leaves the
figures' commands unrunnable without a sign."""

from __future__ import annotations

import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

from fms_dispatch import cli

REPO = Path(__file__).resolve().parent.parent
DOCS = [REPO / "README.md", REPO / "models" / "README.md", *sorted((REPO / "docs").glob("*.md"))]
OPTION = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*)")
#: subcommands whose options belong to a second word (``fms bench bu``, ``fms send order``)
NESTED = {"bench", "send", "experiment"}


def _snippets(text: str) -> list[str]:
    """The code in ``text``: each line of its fenced blocks, and each inline ``code`` span."""
    fenced = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)
    lines = [line.split("  #")[0] for block in fenced.findall(text) for line in block.splitlines()]
    spans = fenced.sub("", text).split("`")[1::2]
    return lines + spans


def _commands() -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """Per bench script and per fms subcommand (``"solve"``, ``"bench bu"``), the long options the docs pass it."""
    bench: dict[str, set[str]] = defaultdict(set)
    fms: dict[str, set[str]] = defaultdict(set)
    for path in DOCS:
        for code in _snippets(path.read_text()):
            code = code.strip().removeprefix("nice ")
            m = re.match(r"python bench/(\w+)\.py", code)
            if m:
                bench[m.group(1)].update(OPTION.findall(code))
            words = code.split()
            if len(words) < 2 or words[0] != "fms" or not re.match(r"[a-z]+$", words[1]):
                continue
            subs = [words[1]]
            if words[1] in NESTED and len(words) > 2 and re.fullmatch(r"[a-z|]+", words[2]):
                subs = [f"{words[1]} {w}" for w in words[2].split("|")]  # `fms experiment a|b|c`
            for sub in subs:
                fms[sub].update(OPTION.findall(code))
    return bench, fms


BENCH, FMS = _commands()


def test_the_docs_give_commands_to_check() -> None:
    # the patterns above must find the docs' commands at all (a check that finds none passes for nothing)
    assert len(BENCH) >= 15 and {"decide_speed", "heldout", "validation"} <= set(BENCH)
    assert {"solve", "up", "train", "replay", "bench bu", "bench sl", "send order", "experiment ablation"} <= set(FMS)
    assert "--guide-tabu" in FMS["solve"] and "--parts" in BENCH["decide_speed"]


@pytest.mark.parametrize("script", sorted(BENCH))
def test_a_documented_bench_command_runs_with_its_options(script: str) -> None:
    path = REPO / "bench" / f"{script}.py"
    assert path.exists(), f"the docs run bench/{script}.py, which does not exist"
    res = subprocess.run([sys.executable, str(path), "--help"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    missing = sorted(BENCH[script] - set(OPTION.findall(res.stdout)))
    assert not missing, f"bench/{script}.py does not take {missing}, which the docs pass it"


@pytest.mark.parametrize("sub", sorted(FMS))
def test_a_documented_fms_command_takes_its_options(sub: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        cli.main([*sub.split(), "--help"])
    assert done.value.code == 0
    taken = set(OPTION.findall(capsys.readouterr().out))
    missing = sorted(FMS[sub] - taken)
    assert not missing, f"fms {sub} does not take {missing}, which the docs pass it"


def test_the_readmes_python_example_runs() -> None:
    """README.md's Python section runs as written (each of its asserts holds), in a fresh interpreter."""
    text = (REPO / "README.md").read_text()
    blocks = re.findall(r"^```python\n(.*?)^```", text, re.S | re.M)
    assert blocks, "README.md has no Python example"
    for code in blocks:
        res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=REPO)
        assert res.returncode == 0, res.stderr
