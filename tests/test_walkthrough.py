"""docs/walkthrough.md runs as a doctest, each section on its own, in time, and its pictures are drawn.

    pytest tests/test_walkthrough.py                  # the test (pictures to a temporary folder)
    python tests/test_walkthrough.py                  # the same run, by hand, from the repository root
    python tools/walkthrough_figures.py               # the same run, redrawing the pictures in docs/img

The running and the drawing are tools/walkthrough_figures.py's (loaded from its path: tools/ is not
a package). Run as a script, Python puts tests/ (not the repository root) first on sys.path, so
`import pyvf` finds the installed package, not the unbuilt source tree.
"""

import importlib.util
import os
import re
import sys
import unicodedata

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS = os.path.join(ROOT, "docs")
TIME_LIMIT_S = 120  # the walkthrough promises under two minutes; it takes about 5 s alone, 15 s on 2 busy cores


def _figures_tool():
    spec = importlib.util.spec_from_file_location("walkthrough_figures",
                                                  os.path.join(ROOT, "tools", "walkthrough_figures.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _text():
    with open(os.path.join(DOCS, "walkthrough.md"), encoding="utf-8") as f:
        return f.read()


def _anchor(heading):
    """GitHub's anchor of a markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    kept = "".join(c for c in heading.strip().lower()
                   if c in " -_" or unicodedata.category(c)[0] in "LN")
    return kept.replace(" ", "-")


def test_walkthrough_runs_section_by_section(tmp_path):
    from PIL import Image

    tool = _figures_tool()
    runs, seconds = tool.run_sections()
    titles = [t for t, _, _ in runs]
    assert [int(t.split(".")[0]) for t in titles[1:]] == list(range(1, 8)), f"sections 1..7 expected, got {titles}"
    for title, result, _ in runs[1:]:  # each numbered section runs alone: it imports what it needs
        assert result.attempted > 0, f"section {title!r} of docs/walkthrough.md has no examples"
    failed = [(t, r.failed) for t, r, _ in runs if r.failed]
    assert not failed, f"examples of docs/walkthrough.md failed (above), by section: {failed}"
    assert seconds < TIME_LIMIT_S, f"docs/walkthrough.md took {seconds:.0f} s, the limit is {TIME_LIMIT_S} s"

    written = tool.draw_figures(runs, tmp_path)
    shown = set(re.findall(r"\]\(img/(walkthrough-[\w-]+\.png)\)", _text()))
    committed = {f for f in os.listdir(os.path.join(DOCS, "img")) if f.startswith("walkthrough-")}
    assert shown == set(tool.FIGURES), f"pictures shown {sorted(shown)} != pictures drawn {sorted(tool.FIGURES)}"
    assert committed == shown, f"docs/img/walkthrough-*.png {sorted(committed)} != pictures shown {sorted(shown)}"
    for path in written:
        name = os.path.basename(path)
        with Image.open(path) as a, Image.open(os.path.join(DOCS, "img", name)) as b:
            assert a.size == b.size, (f"{name}: drawn {a.size}, the committed copy is {b.size}: "
                                      "regenerate it (python tools/walkthrough_figures.py)")
            pixels = a.convert("L").getextrema()
            assert pixels[0] < 100 and pixels[1] > 200, f"{name} is blank"


def test_tree_picture_edges_come_from_the_mask():
    """The tree picture's edge into each node is the last trunk view it attends (besides itself)."""
    import pyvf

    parents = _figures_tool()._tree_layout(pyvf.branching_mask(3, 4, 1), 4)
    assert parents[(0, 0)] is None and parents[(1, 0)] is None and parents[(2, 0)] is None
    for r in range(3):
        for i in range(1, 4):
            assert parents[(r, i)] == (0, i - 1)


def test_walkthrough_links_name_its_headings():
    """Every `#anchor` the walkthrough links (to itself, math.md, accuracy.md) names a heading there."""
    text = _text()
    bad = []
    for target, anchor in re.findall(r"\]\(([\w./-]*)#([^)\s]+)\)", text):
        path = os.path.join(DOCS, target) if target else os.path.join(DOCS, "walkthrough.md")
        with open(path, encoding="utf-8") as f:
            headings = {_anchor(h) for h in re.findall(r"^#+ (.+)$", f.read(), flags=re.M)}
        if anchor not in headings:
            bad.append(f"{target}#{anchor}")
    assert not bad, f"docs/walkthrough.md links to headings that do not exist: {bad}"
    assert _anchor("§4 The codebook") == "4-the-codebook"  # the rule itself, on a known GitHub anchor


def test_printed_output_is_compared_in_full(tmp_path):
    """No ELLIPSIS: the walkthrough's output is checked as printed (its mask rows are made of dots,
    which ELLIPSIS would read as "anything"); a wrong row of the mask fails."""
    import doctest

    tool = _figures_tool()
    assert not tool.OPTIONS & doctest.ELLIPSIS
    text = _text()
    section = next(chunk for title, _, chunk in tool.split_sections(text) if title.startswith("2."))
    assert "  gen view 2  ##.. ..#. ...." in section
    wrong = tmp_path / "walkthrough.md"
    wrong.write_text(section.replace("  gen view 2  ##.. ..#. ....", "  gen view 2  #... ..#. ....", 1),
                     encoding="utf-8")
    runs, _ = tool.run_sections(path=str(wrong))
    assert sum(r.failed for _, r, _ in runs) == 1


def main(argv):
    tool = _figures_tool()
    return tool.main(["--no-pictures"] + argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
