"""docs/walkthrough.md runs as a doctest: every example passes, the pictures are written, in time.

    pytest tests/test_walkthrough.py                  # the test (pictures to a temporary folder)
    python tests/test_walkthrough.py                  # the same run, by hand, from the repository root
    python tests/test_walkthrough.py --out docs/img   # regenerate the pictures the walkthrough shows

Run as a script, Python puts tests/ (not the repository root) first on sys.path, so `import pyvf`
finds the installed package, not the unbuilt source tree.
"""

import doctest
import os
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS = os.path.join(ROOT, "docs")
WALKTHROUGH = os.path.join(DOCS, "walkthrough.md")
PICTURES = ("walkthrough-mask.png", "walkthrough-render.png")  # what the walkthrough writes, shown from docs/img
TIME_LIMIT_S = 120  # the bound for the whole file; it takes about 15 s on 2 cores
OPTIONS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def run_walkthrough(out, verbose=False):
    """Run every example of docs/walkthrough.md, the pictures written to `out`, from a temporary
    working folder. Returns (doctest.TestResults, seconds). numpy's print options are restored."""
    env = {"PYVF_DOCS": DOCS, "PYVF_WALKTHROUGH_OUT": os.path.abspath(out)}
    saved_env = {k: os.environ.get(k) for k in env}
    saved_print = np.get_printoptions()
    cwd = os.getcwd()
    t0 = time.perf_counter()
    try:
        os.environ.update(env)
        with tempfile.TemporaryDirectory() as work:
            os.chdir(work)
            result = doctest.testfile(WALKTHROUGH, module_relative=False, optionflags=OPTIONS, verbose=verbose,
                                      report=True, encoding="utf-8")
    finally:
        os.chdir(cwd)
        np.set_printoptions(**saved_print)
        for k, v in saved_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return result, time.perf_counter() - t0


def test_walkthrough_runs(tmp_path):
    from PIL import Image

    out = tmp_path / "pictures"
    result, seconds = run_walkthrough(out)
    assert result.attempted > 0, "docs/walkthrough.md has no examples"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples of docs/walkthrough.md failed (above)"
    assert seconds < TIME_LIMIT_S, f"docs/walkthrough.md took {seconds:.0f} s, the limit is {TIME_LIMIT_S} s"
    for name in PICTURES:
        written = out / name
        assert written.is_file(), f"the walkthrough did not write {name}"
        shown = os.path.join(DOCS, "img", name)
        assert os.path.isfile(shown), f"docs/img/{name}, the committed copy the walkthrough shows, is missing"
        with Image.open(written) as a, Image.open(shown) as b:
            assert a.size == b.size, f"{name}: written {a.size}, the committed copy is {b.size}: regenerate it"
            if name == "walkthrough-mask.png":  # exact integer drawing: the committed copy must match to the pixel
                assert np.array_equal(np.asarray(a), np.asarray(b)), \
                    f"docs/img/{name} differs from what the walkthrough draws: regenerate it (module docstring)"


def main(argv):
    import argparse

    p = argparse.ArgumentParser(description="Run docs/walkthrough.md as a doctest.")
    p.add_argument("--out", default=None, help="folder for the pictures (default: a temporary folder); "
                                               "docs/img regenerates the committed copies")
    p.add_argument("-v", "--verbose", action="store_true", help="print every example as it runs")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or tmp
        os.makedirs(out, exist_ok=True)
        result, seconds = run_walkthrough(out, verbose=args.verbose)
        print(f"docs/walkthrough.md: {result.attempted} examples, {result.failed} failed, {seconds:.1f} s; "
              f"pictures: {', '.join(os.path.join(args.out, n) for n in PICTURES) if args.out else 'not kept'}")
    return 1 if result.failed or not result.attempted else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
