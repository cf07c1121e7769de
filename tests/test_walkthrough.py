"""docs/walkthrough.md runs as a doctest, each section on its own, in time, and its pictures are drawn;
what its text claims beyond the printed output is checked here, on the arrays its sections computed.
The running and the drawing are tools/walkthrough_figures.py's (`python tools/walkthrough_figures.py`
redraws the pictures in docs/img), loaded from its path: tools/ is not a package.
"""

import importlib.util
import json
import os
import re

import numpy as np
import pytest

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


@pytest.fixture(scope="module")
def sections():
    """The walkthrough run once, section by section: (runs, seconds, {section number: namespace})."""
    runs, seconds = _figures_tool().run_sections()
    spaces = {int(t.split(".")[0]): ns for t, _, ns in runs if t[0].isdigit()}
    return runs, seconds, spaces


def test_walkthrough_runs_section_by_section(sections, tmp_path):
    from PIL import Image

    tool = _figures_tool()
    runs, seconds, _ = sections
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


# What the walkthrough's text claims beyond what its examples print, checked on the arrays its
# sections left behind: the plumbing (tolerances, layouts, report files) lives here, not in the text.


def test_section_1_codebook_claims(sections):
    """The tokens are code 0 where a patch is pure background (the view has both kinds) and the C++
    kernel's nearest of codes 1..V-1 elsewhere; the loss is rec + weight * L_c, and L_c's
    gradient joins the straight-through one; the EMA step follows math.md §4 line by line."""
    import pyvf

    ns = sections[2][1]
    codebook, x, out, E, empty = ns["codebook"], ns["x"], ns["out"], ns["E"], ns["empty"].reshape(8, 8)
    cells = np.ascontiguousarray(ns["z"].reshape(64, 64).T)  # the kernel takes C-contiguous (M, D) and (V, D)
    nearest, _ = pyvf.vq_nearest(cells, np.ascontiguousarray(E[:, 1:].T))
    assert empty.any() and not empty.all()
    assert np.array_equal(np.where(empty, 0, 1 + nearest.reshape(8, 8)), out.codes[0])
    assert np.array_equal(ns["tokens"][0], out.codes[0])
    assert ns["tokens"].shape == (15, 8, 8) and 0 <= ns["tokens"].min() and ns["tokens"].max() < 256
    w = codebook.config.codebook_weight
    assert np.isclose(out.loss, out.rec_loss + w * out.commitment_loss)  # float32 sums: default rtol
    out = codebook.forward(x[:1], trace=True)
    g = codebook.backward()  # the gradient of the loss: d L_c / d z = 2 w (z - e) / z.size joins in
    z, e = out.trace["quant_conv"][0], E[:, out.codes[0]]
    # float32 gradients summed in another order: rtol 1e-4; atol far below the entries' size (~1e-6)
    assert np.allclose(g["quant_conv"][0], g["quantize"][0] + 2 * w * (z - e) / z.size, rtol=1e-4, atol=1e-9)

    # EMA, by hand (math.md §4): averages from 0, bias correction at counter 1, Laplace smoothing
    quant, vecs, codes, before = ns["quant"], ns["vecs"], ns["codes"], ns["before"]
    decay, eps, V = quant.decay, quant.eps, before.shape[1]
    cs = (1 - decay) * np.bincount(codes, minlength=V) / (1 - decay)
    dw = (1 - decay) * np.stack([vecs[codes == c].sum(axis=0) for c in range(V)], axis=1) / (1 - decay)
    n = cs.sum()
    # float64, a handful of operations in another order: rtol 1e-12
    assert np.allclose(quant.embeddings, dw / ((cs + eps) / (n + V * eps) * n), rtol=1e-12, atol=0)
    assert quant.counter == 1
    q = ns["q_out"].quantized.reshape(2, 4).T  # the step's output used the codes from before it
    assert np.array_equal(q, before.T[codes])


def test_section_2_tree_claims(sections):
    """Each '#' of the printed mask is a 4x4 square with 4 tokens per view; the scaling report's
    fitted memory slopes (forward+backward bytes against the number of views) are about 1 for the
    tree and 2 for the stacked sequences, as the text says."""
    ns = sections[2][2]
    assert int(ns["m4"].sum()) == 16 * int(ns["m"].sum())
    with open(os.path.join(DOCS, "measurements", "scaling-H4-dh32.json"), encoding="utf-8") as f:
        slopes = json.load(f)["slopes"]["4x32"]
    assert 0.8 < slopes["pyvf"]["fb_bytes"] < 1.25 and 1.75 < slopes["naive_pyvf"]["fb_bytes"] < 2.25


def test_section_4_transformer_claims(sections):
    """make_relative is undone by absolute_poses; the rows and the heads equal the text's formulas to
    float64 rounding; the per-token positions are the raw head output over pose_multiplier."""
    import pyvf

    ns = sections[2][4]
    out, p, V, cams = ns["out"], ns["p"], ns["V"], ns["cams"]
    back = pyvf.absolute_poses(ns["poses"], ns["first"][:, None])  # float64 round trip: default rtol, 1e-6 degrees
    assert np.allclose(back[..., :3], cams[..., :3]) and pyvf.orientation_error(back[..., 3:], cams[..., 3:]).max() < 1e-6
    # float64, the same products summed in another order: rtol 1e-12, atol for entries near 0
    assert np.allclose(out.trace["embed.out"], ns["rows"], rtol=1e-12, atol=1e-15)
    assert np.allclose(out.logits, out.trace["ln_f.generation"] @ p["wte/weight"][:V].T, rtol=1e-12, atol=1e-14)
    assert np.allclose(out.pose_prediction[..., :3], out.pose_raw[..., :3] / 0.2)
    assert np.allclose(ns["ce"], out.ce_loss, rtol=1e-12) and np.allclose(ns["pose"], out.pose_loss, rtol=1e-12)


def test_section_5_the_loss_falls(sections):
    """The toy run learns: the loss halves, the cross-entropy falls 4x in 30 steps."""
    history = sections[2][5]["history"]
    assert history[-1][0] < 0.5 * history[0][0] and history[-1][1] < 0.25 * history[0][1]


def test_printed_output_is_compared_in_full():
    """No ELLIPSIS: the walkthrough's output is checked as printed (its mask rows are made of dots,
    which ELLIPSIS would read as "anything")."""
    import doctest

    assert not _figures_tool().OPTIONS & doctest.ELLIPSIS

