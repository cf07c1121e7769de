"""Every reference in the repository resolves inside it: relative links of the README and docs/
(to a file, and to a heading of a markdown file),
and each `math.md §N` (in docs and code) names a section of docs/math.md."""

import os
import re
import subprocess
import unicodedata

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _tracked(*suffixes):
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    return [f for f in files if f.endswith(suffixes)]


MARKDOWN = [f for f in _tracked(".md") if f == "README.md" or f.startswith("docs/")]


@pytest.mark.parametrize("doc", MARKDOWN)
def test_relative_links_resolve(doc):
    with open(os.path.join(ROOT, doc), encoding="utf-8") as f:
        text = f.read()
    bad = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+://|mailto:", target):
            continue
        file, _, anchor = target.partition("#")
        path = os.path.normpath(os.path.join(ROOT, os.path.dirname(doc), file or os.path.basename(doc)))
        if not os.path.exists(path) or anchor and path.endswith(".md") and anchor not in _anchors(path):
            bad.append(target)
    assert not bad, f"{doc} links to files or headings the repository does not have: {bad}"
    assert _anchor("§4 The codebook") == "4-the-codebook"  # GitHub's rule, on a known anchor


def _anchor(heading):
    """GitHub's anchor of a markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    return "".join(c for c in heading.strip().lower() if c in " -_" or unicodedata.category(c)[0] in "LN").replace(" ", "-")


def _anchors(path):
    with open(path, encoding="utf-8") as f:
        return {_anchor(h) for h in re.findall(r"^#+ (.+)$", f.read(), flags=re.M)}


def test_section_references_name_sections_of_math_md():
    with open(os.path.join(ROOT, "docs", "math.md"), encoding="utf-8") as f:
        sections = set(re.findall(r"^## §(\d+) ", f.read(), flags=re.M))
    assert sections == {str(i) for i in range(1, 8)}
    refs, bad = 0, []
    for name in _tracked(".py", ".md", ".cpp", ".h", ".txt"):
        with open(os.path.join(ROOT, name), encoding="utf-8") as f:
            text = f.read()
        for n in re.findall(r"math\.md,? ?\n?\s*§(\d+)", text):
            refs += 1
            if n not in sections:
                bad.append((name, n))
    assert refs > 50 and not bad, bad
