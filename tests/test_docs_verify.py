"""docs/verify.md runs as written: its Python blocks, in order, in one namespace (in a temporary
folder), each printing exactly the text block that follows it. The page opens with the result of
its example, a text block that follows no Python block: each of its lines must be a line some
block prints. The printed numbers in the doc are this run's: after a change, regenerate them with

    python tests/test_docs_verify.py --update

(run from outside the repository root, so that the installed pyvf is imported) and review the diff.

Numbers at the level of float64 rounding (below 1e-9: the errors of quantities that agree) may
differ in their digits from machine to machine (BLAS summation order, the kernels' instruction
set), so there the check is only that both are below 1e-9; every other number and word must be
exactly what the doc shows."""

import contextlib
import io
import os
import re
import sys


DOC = os.path.join(os.path.dirname(__file__), "..", "docs", "verify.md")
NUMBER = re.compile(r"[-+]?\d+\.\d+e[-+]\d+")
ROUNDING = 1e-9


def same_output(printed, shown):
    """printed == shown, but for rounding-level numbers (both below ROUNDING)."""
    a, b = NUMBER.split(printed), NUMBER.split(shown)
    na, nb = NUMBER.findall(printed), NUMBER.findall(shown)
    if a != b or len(na) != len(nb):
        return False
    return all(x == y or (abs(float(x)) < ROUNDING and abs(float(y)) < ROUNDING) for x, y in zip(na, nb))


BLOCK = re.compile(r"```python\n(.*?)```(\n\n```text\n(.*?)```)?", flags=re.S)
TEXT = re.compile(r"```text\n(.*?)```", flags=re.S)


def standalone_text(text):
    """The text blocks that follow no Python block (the opening result): [match]."""
    shown = {m.start(2) + 2 for m in BLOCK.finditer(text) if m.group(2)}
    return [m for m in TEXT.finditer(text) if m.start() not in shown]


def printed_line(line, printed):
    """The line of `printed` (all blocks' output) that `line` shows, or None."""
    return next((p for p in printed if same_output(p, line)), None)


def run_blocks(text):
    """-> [(match, the block's printed output)], every Python block run in order."""
    namespace, results = {"__name__": "verify_md"}, []
    for i, m in enumerate(BLOCK.finditer(text)):
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            exec(compile(m.group(1), f"docs/verify.md python block {i}", "exec"), namespace)
        results.append((m, out.getvalue()))
    return results


def test_docs_verify_runs_and_prints_what_it_says(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with open(DOC) as f:
        text = f.read()
    results = run_blocks(text)
    lines = [line for _, p in results for line in p.splitlines()]  # everything the page's blocks print
    assert len(results) >= 5
    checked = 0
    for i, (m, printed) in enumerate(results):
        if m.group(2) is None:
            assert printed == "", f"block {i} prints but the doc shows no output:\n{printed}"
            continue
        assert same_output(printed, m.group(3)), (f"block {i} printed\n{printed}\nbut the doc says\n{m.group(3)}\n"
                                       "(regenerate: python tests/test_docs_verify.py --update)")
        checked += 1
    assert checked >= 4
    assert same_output("x 1.234e-16 y", "x 5.000e-17 y") and not same_output("x 1.2e-03", "x 1.3e-03")
    # the opening: the page's first block, before the first section, is the example's result, and
    # every line of it is printed by the run
    opening = standalone_text(text)
    assert len(opening) == 1 and opening[0].start() == text.index("```") < text.index("\n## "), opening
    for line in opening[0].group(1).splitlines():
        assert printed_line(line, lines), f"the opening shows a line no block prints: {line!r}"
    # what the walkthrough claims, independently of the printed text (--update cannot rewrite it)
    transformer = {"compare, the first wrong quantity: blocks.0.attn.c_proj",  # the q, k, v order
                   "teacher_force, the wrong layers: ['blocks.0.attn', 'blocks.1.attn']"}  # one class, both blocks
    claims = transformer | {"compare, the first wrong quantity: encoder.down.0.downsample.conv",  # the padding
                            "teacher_force, the wrong layers: ['encoder.down.0.downsample']",
                            "first wrong quantity: None, largest error 1.0e-16"}  # pyvf's port: any error < 1e-9
    missing = [c for c in claims if not printed_line(c, lines)]
    assert not missing, missing
    assert transformer <= set(opening[0].group(1).splitlines()), "the page must open with the transformer's result"


def update():
    with open(DOC) as f:
        text = f.read()
    pieces, pos = [], 0
    results = run_blocks(text)
    for m, printed in results:
        pieces.append(text[pos:m.start()])
        block = f"```python\n{m.group(1)}```"
        if printed:
            block += f"\n\n```text\n{printed}```"
        pieces.append(block)
        pos = m.end()
    pieces.append(text[pos:])
    text, lines = "".join(pieces), [line for _, p in results for line in p.splitlines()]
    skeleton = lambda line: NUMBER.sub("#", line)  # noqa: E731
    for m in reversed(standalone_text(text)):  # the opening: each line as printed now, found by its words
        new = [next((p for p in lines if skeleton(p) == skeleton(old)), old) for old in m.group(1).splitlines()]
        text = text[:m.start(1)] + "".join(line + "\n" for line in new) + text[m.end(1):]
    with open(DOC, "w") as f:
        f.write(text)


if __name__ == "__main__":
    if sys.argv[1:] != ["--update"]:
        sys.exit(__doc__)
    update()
