"""docs/verify.md runs as written: its Python blocks, in order, in one namespace (in a temporary
folder), each printing exactly the text block that follows it. The printed numbers in the doc
are this run's: after a change, regenerate them with

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
    # what the walkthrough claims, independently of the printed text
    ns_first = [p for m, p in results if "report.first" in m.group(1)][0]
    assert ns_first.splitlines()[0] == "blocks.0.attn.c_proj"
    ns_teacher = [p for m, p in results if "teacher_force" in m.group(1)][0]
    assert ns_teacher.splitlines()[0] == "['blocks.0.attn', 'blocks.1.attn']"


def update():
    with open(DOC) as f:
        text = f.read()
    pieces, pos = [], 0
    for m, printed in run_blocks(text):
        pieces.append(text[pos:m.start()])
        block = f"```python\n{m.group(1)}```"
        if printed:
            block += f"\n\n```text\n{printed}```"
        pieces.append(block)
        pos = m.end()
    pieces.append(text[pos:])
    with open(DOC, "w") as f:
        f.write("".join(pieces))


if __name__ == "__main__":
    if sys.argv[1:] != ["--update"]:
        sys.exit(__doc__)
    update()
