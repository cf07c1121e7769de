"""Every `pyvf ...` command line quoted in the README and docs/ (in ```bash blocks; ```text blocks
are output) names a command that exists and only options that command has (its argparse parser,
or a benchmark's own --help)."""

import contextlib
import io
import os
import re

import pytest

from pyvf.cli import build_parser, main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS = ["README.md"] + [os.path.join("docs", f) for f in sorted(os.listdir(os.path.join(ROOT, "docs")))
                        if f.endswith(".md")]


def quoted_commands():
    """(doc, line) for each line of a ```bash block that starts with `pyvf ` (after an optional
    environment assignment such as PYVF_ISA=baseline)."""
    out = []
    for doc in DOCS:
        with open(os.path.join(ROOT, doc), encoding="utf-8") as f:
            blocks = re.findall(r"```(?:bash|sh|shell)\n(.*?)```", f.read(), flags=re.S)
        for block in blocks:
            for line in block.splitlines():
                line = re.sub(r"^([A-Z_]+=\S+\s+)+", "", line.strip())
                if line.startswith("pyvf "):
                    out.append((doc, line.split("#")[0].strip()))
    return out


def _subparsers():
    parser = build_parser()
    action = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return action.choices


def _bench_options(name):
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), pytest.raises(SystemExit):
        main(["bench", name, "--help"])
    return set(re.findall(r"--[a-z][a-z0-9-]*", buf.getvalue()))


def test_some_commands_are_quoted():
    assert len(quoted_commands()) > 20


@pytest.mark.parametrize("doc, line", quoted_commands())
def test_quoted_command_exists_with_its_options(doc, line):
    words = line.split()
    commands = _subparsers()
    names = words[1].split("|")
    for name in names:
        assert name in commands or name.startswith("-"), f"{doc}: `{line}`: no command {name!r}"
    options = set(re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", line))
    for name in names:
        if name.startswith("-"):
            continue
        if name == "bench":
            # the benchmark's name(s) follow; each has its own parser
            have = set()
            for bench in words[2].split("|"):
                have |= _bench_options(bench)
        else:
            have = set(commands[name]._option_string_actions)
            for action in commands[name]._actions:  # a command with commands of its own (convert)
                if isinstance(action.choices, dict):
                    for sub in action.choices.values():
                        have |= set(sub._option_string_actions)
        missing = sorted(options - have - {"--help", "--version"})
        assert not missing, f"{doc}: `{line}`: `pyvf {name}` has no option {missing}"


def test_no_quoted_command_is_a_placeholder():
    """A command a reader copies runs as written: no `pyvf ... ...` with its arguments left out,
    in a ```bash block or inline."""
    bad = [(doc, line) for doc, line in quoted_commands() if "..." in line]
    for doc in DOCS:
        with open(os.path.join(ROOT, doc), encoding="utf-8") as f:
            bad += [(doc, c) for c in re.findall(r"`(pyvf [^`]*)`", f.read()) if "..." in c]
    assert not bad, f"commands with arguments left out: {bad}"
