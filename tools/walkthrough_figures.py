"""Run docs/walkthrough.md, each section on its own, and draw its pictures (docs/img/walkthrough-*.png).

    python tools/walkthrough_figures.py                 # run every example, redraw the pictures in docs/img/
    python tools/walkthrough_figures.py --out DIR       # the pictures elsewhere
    python tools/walkthrough_figures.py --no-pictures   # only run the examples

The walkthrough is a doctest. Each `## N.` section runs in a fresh namespace (so each must import
and compute what it needs), from a temporary working folder, with PYVF_DOCS set to docs/. The
pictures are drawn, with Pillow only, from the arrays the sections leave in their namespaces: a
picture shows exactly what the walkthrough computed and checked. Nothing is drawn when an example
fails. tests/test_walkthrough.py runs the same code (pictures to a temporary folder).
"""

import argparse
import colorsys
import doctest
import os
import re
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS = os.path.join(ROOT, "docs")
WALKTHROUGH = os.path.join(DOCS, "walkthrough.md")
OPTIONS = doctest.NORMALIZE_WHITESPACE  # no ELLIPSIS: the printed mask's dots are compared, not read as "anything"

_WHITE, _BLACK, _GREY, _LIGHT = (255, 255, 255), (0, 0, 0), (150, 150, 150), (215, 215, 215)
_TRUNK, _GEN, _LOC = (60, 60, 60), (8, 153, 193), (255, 33, 40)  # the paper's colours for the branches


# ---------------------------------------------------------------------------------------
# running the walkthrough


def split_sections(text):
    """The walkthrough's text -> [(title, first line number (0-based), text)]: the part before the
    first `## ` heading (title "intro"), then one entry per `## ` section."""
    starts = [0] + [m.start() for m in re.finditer(r"^## ", text, flags=re.M)]
    out = []
    for a, b in zip(starts, starts[1:] + [len(text)]):
        chunk = text[a:b]
        title = chunk.splitlines()[0][3:].strip() if chunk.startswith("## ") else "intro"
        out.append((title, text.count("\n", 0, a), chunk))
    return out


def run_sections(verbose=False, path=WALKTHROUGH):
    """Run every section of the walkthrough in its own namespace. Returns ([(title,
    doctest.TestResults, namespace)], seconds). Failures are reported on stdout by doctest.
    The working folder, PYVF_DOCS and numpy's print options are restored afterwards."""
    with open(path, encoding="utf-8") as f:
        text = f.read()
    saved_env, saved_print, cwd = os.environ.get("PYVF_DOCS"), np.get_printoptions(), os.getcwd()
    parser, runs = doctest.DocTestParser(), []
    t0 = time.perf_counter()
    try:
        os.environ["PYVF_DOCS"] = DOCS
        with tempfile.TemporaryDirectory() as work:
            os.chdir(work)
            for title, line, chunk in split_sections(text):
                test = parser.get_doctest(chunk, {"__name__": "walkthrough"}, f"walkthrough: {title}", path, line)
                runner = doctest.DocTestRunner(verbose=verbose, optionflags=OPTIONS)
                result = runner.run(test, clear_globs=False)
                runs.append((title, result, test.globs))
    finally:
        os.chdir(cwd)
        np.set_printoptions(**saved_print)
        if saved_env is None:
            os.environ.pop("PYVF_DOCS", None)
        else:
            os.environ["PYVF_DOCS"] = saved_env
    return runs, time.perf_counter() - t0


# ---------------------------------------------------------------------------------------
# drawing helpers (Pillow)


def _pil():
    from PIL import Image, ImageDraw, ImageFont  # a dependency of pyvf

    return Image, ImageDraw, ImageFont


def _font(size=12):
    """Pillow's default font at `size` (FreeType), or its fixed bitmap font without FreeType."""
    ImageFont = _pil()[2]
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, ImportError, OSError):  # older Pillow or no FreeType
        return ImageFont.load_default()


def _code_colour(k):
    """A colour per code index, spread around the hue circle (equal codes, equal colours)."""
    r, g, b = colorsys.hsv_to_rgb((k * 0.618034) % 1.0, 0.55, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


def _tile(img, scale):
    """(S, S, 3) uint8 -> PIL image, enlarged `scale` times by nearest neighbour."""
    Image = _pil()[0]
    return Image.fromarray(np.ascontiguousarray(img.repeat(scale, axis=0).repeat(scale, axis=1)))


def _token_map(codes, cell, numbers=False, font=None):
    """(k, k) code indices -> PIL image of k x k cells, coloured by code, optionally numbered."""
    Image, ImageDraw, _ = _pil()
    k = codes.shape[0]
    img = Image.new("RGB", (k * cell, k * cell), _WHITE)
    draw = ImageDraw.Draw(img)
    for i in range(k):
        for j in range(k):
            box = [j * cell, i * cell, (j + 1) * cell - 1, (i + 1) * cell - 1]
            draw.rectangle(box, fill=_code_colour(int(codes[i, j])), outline=_WHITE if numbers else None)
            if numbers:
                t = str(int(codes[i, j]))
                w = draw.textlength(t, font=font)
                draw.text((j * cell + (cell - w) / 2, i * cell + cell / 2 - 7), t, fill=_BLACK, font=font)
    return img


def _arrow(draw, a, b, colour=_BLACK, width=2, head=7):
    (x0, y0), (x1, y1) = a, b
    draw.line([a, b], fill=colour, width=width)
    d = np.array([x1 - x0, y1 - y0], float)
    d /= max(np.linalg.norm(d), 1e-9)
    n = np.array([-d[1], d[0]])
    tip = np.array([x1, y1], float)
    pts = [tuple(tip), tuple(tip - head * d + head * 0.5 * n), tuple(tip - head * d - head * 0.5 * n)]
    draw.polygon(pts, fill=colour)


def _centered(draw, text, x0, width, y, font, fill=_BLACK):
    draw.text((x0 + (width - draw.textlength(text, font=font)) / 2, y), text, fill=fill, font=font)


# ---------------------------------------------------------------------------------------
# the pictures, each from one section's namespace


def tokens_figure(ns):
    """Section 1: view 0, its 8x8 token map (code indices), the decoder's picture of it."""
    Image, ImageDraw, _ = _pil()
    font, small, big = _font(12), _font(11), _font(14)
    image, codes, recon = ns["images"][0], ns["tokens"][0], ns["recon"][0]
    T, gap, top = 256, 84, 46
    sheet = Image.new("RGB", (3 * T + 2 * gap + 20, top + T + 30), _WHITE)
    draw = ImageDraw.Draw(sheet)
    draw.text((10, 6), "Section 1: an image becomes 8x8 tokens (the shipped codebook, scene seed 7, view 0)",
              fill=_BLACK, font=big)
    x = [10, 10 + T + gap, 10 + 2 * (T + gap)]
    sheet.paste(_tile(image, T // image.shape[0]), (x[0], top))
    sheet.paste(_token_map(codes, T // codes.shape[0], numbers=True, font=small), (x[1], top))
    sheet.paste(_tile(recon, T // recon.shape[0]), (x[2], top))
    for xa, label in zip(x, (f"view 0: {image.shape[0]}x{image.shape[1]} pixels",
                              f"its {codes.shape[0]}x{codes.shape[1]} tokens (code index)",
                              "decoded from the tokens")):
        _centered(draw, label, xa, T, top + T + 8, font)
    for a, lines in ((0, ("encoder,", "nearest code")), (1, ("decoder",))):
        xa = x[a] + T + 6
        _arrow(draw, (xa, top + T // 2), (xa + gap - 12, top + T // 2))
        for j, line in enumerate(lines):
            draw.text((xa, top + T // 2 - 16 * (len(lines) - j) - 4), line, fill=_BLACK, font=small)
    return sheet


def ema_figure(ns):
    """Section 1: the EMA step in 2-D: vectors, codes before and after, arrows."""
    Image, ImageDraw, _ = _pil()
    font, big = _font(12), _font(14)
    vecs, before, after, codes = ns["vecs"], ns["before"], ns["new_codes"], ns["q_out"].codes.ravel()
    W, H, left, top, P = 580, 440, 50, 40, 340  # plot area P x P
    lo, hi = -0.5, 4.5
    px = lambda p: (left + (p[0] - lo) / (hi - lo) * P, top + P - (p[1] - lo) / (hi - lo) * P)
    sheet = Image.new("RGB", (W, H), _WHITE)
    draw = ImageDraw.Draw(sheet)
    draw.text((10, 8), "Section 1: one EMA step of the quantizer (decay 0.99, from zero averages)", fill=_BLACK, font=big)
    draw.rectangle([left, top, left + P, top + P], outline=_GREY)
    for t in range(5):  # ticks and grid
        x, y = px((t, t))
        draw.line([x, top, x, top + P], fill=(235, 235, 235))
        draw.line([left, y, left + P, y], fill=(235, 235, 235))
        draw.text((x - 3, top + P + 4), str(t), fill=_BLACK, font=font)
        draw.text((left - 14, y - 7), str(t), fill=_BLACK, font=font)
    draw.text((left + P / 2 - 30, top + P + 20), "dimension 0", fill=_BLACK, font=font)
    draw.text((4, top - 16), "dim 1", fill=_BLACK, font=font)
    colours = [_GEN, _LOC, (40, 160, 60)]
    for c in range(before.shape[1]):
        a, b = px(before[:, c]), px(after[:, c])
        if np.hypot(a[0] - b[0], a[1] - b[1]) > 12:
            _arrow(draw, a, b, colour=colours[c], width=2)
        draw.ellipse([a[0] - 8, a[1] - 8, a[0] + 8, a[1] + 8], outline=colours[c], width=2)
        draw.ellipse([b[0] - 5, b[1] - 5, b[0] + 5, b[1] + 5], fill=colours[c])
        draw.text((a[0] + 10, a[1] - 18), f"code {c}", fill=colours[c], font=font)
    for v, c in zip(vecs, codes):
        x, y = px(v)
        draw.line([x - 4, y - 4, x + 4, y + 4], fill=colours[c], width=2)
        draw.line([x - 4, y + 4, x + 4, y - 4], fill=colours[c], width=2)
    legend = ("circle: a code before the step", "dot: the same code after it", "arrow: its move",
              "cross: an encoder vector, in", "the colour of its nearest code", "",
              "code 2: chosen by no vector,", "falls to (0, 0)")
    for i, line in enumerate(legend):
        draw.text((left + P + 14, top + 6 + 16 * i), line, fill=_BLACK, font=_font(11))
    return sheet


def _tree_layout(mask, n):
    """branching_mask(3, n, 1) -> {(r, i): parent (0, j) or None}: the last trunk view a node
    attends besides itself (the tree's edge into the node)."""
    parents = {}
    for r in range(3):
        for i in range(n):
            seen = [j for j in range(n) if mask[r * n + i, j] and (r, j) != (0, i)]
            parents[(r, i)] = (0, max(seen)) if seen else None
    return parents


def tree_figure(ns):
    """Section 2: the tree with its branches, edges read from branching_mask(3, n, 1)."""
    Image, ImageDraw, _ = _pil()
    font, big = _font(12), _font(14)
    m = ns["m"]
    n = m.shape[0] // 3
    parents = _tree_layout(m, n)
    left, dx, bw, bh = 120, 160, 96, 30
    ys = {1: 70, 0: 160, 2: 250}  # rendering above, trunk in the middle, localization below (as the paper)
    sheet = Image.new("RGB", (left + n * dx + 20, 360), _WHITE)
    draw = ImageDraw.Draw(sheet)
    draw.text((10, 8), f"Section 2: the tree of a sequence of {n} views (pyvf.branching_mask(3, {n}, 1))",
              fill=_BLACK, font=big)
    centre = lambda r, i: (left + i * dx + bw / 2, ys[r] + bh / 2)
    for (r, i), par in parents.items():
        if par is not None:
            (x0, y0), (x1, y1) = centre(*par), centre(r, i)
            start = (x0 + bw / 2, y0)
            end = (x1 - bw / 2 - 2, y1) if r == 0 else (x1 - bw / 2 - 2, y1 + (bh / 2 if r == 1 else -bh / 2) * 0.6)
            _arrow(draw, start, end, colour=_GREY, width=2)
    for r, name in ((1, "rendering row"), (0, "trunk row"), (2, "localization row")):
        draw.text((8, ys[r] + 8), name, fill=_BLACK, font=font)
    for (r, i) in parents:
        label = (f"s{i}, c{i}", f"mask, c{i}", f"s{i}, no pose")[r]
        target = r > 0 and i >= 1  # n_loss_skip = 1: view 0 is pure context
        colour = (_TRUNK, _GEN, _LOC)[r] if (r == 0 or target) else _LIGHT
        x0, y0 = left + i * dx, ys[r]
        draw.rounded_rectangle([x0, y0, x0 + bw, y0 + bh], radius=8, outline=colour, width=3,
                               fill=_WHITE)
        _centered(draw, label, x0, bw, y0 + 8, font)
    foot = ("s_i: view i's tokens, c_i: its pose; mask: the mask token in place of every token; "
            "no pose: the localization token in place of the pose.",
            "Arrows: the trunk views a node attends (each node also attends its own tokens). "
            "Blue, red: rendering and localization targets;",
            "grey: view 0's endings, no loss target (n_loss_skip = 1). Follow a leaf back to the root: its sequence.")
    for j, line in enumerate(foot):
        draw.text((10, 296 + 18 * j), line, fill=_BLACK, font=_font(11))
    return sheet


def mask_figure(ns):
    """Section 2: branching_mask(3, 4, 4), every query/key token pair, rows and views labelled."""
    Image, ImageDraw, _ = _pil()
    font, big = _font(12), _font(14)
    m = ns["m4"]
    R, N, L, cell = 3, 4, 4, 8
    T = m.shape[0]
    left, top = 130, 92
    side = T * cell
    sheet = Image.new("RGB", (left + side + 190, top + side + 30), _WHITE)
    draw = ImageDraw.Draw(sheet)
    draw.text((10, 8), "Section 2: the branching mask, 3 rows x 4 views x 4 tokens", fill=_BLACK, font=big)
    colours = np.array([_TRUNK, _GEN, _LOC], np.uint8)
    img = np.full((T, T, 3), 255, np.uint8)
    row_of_query = np.repeat(np.arange(R), N * L)
    img[m] = colours[np.broadcast_to(row_of_query[:, None], m.shape)[m]]
    sheet.paste(_tile(img, cell), (left, top))
    for b in range(1, R * N):  # block boundaries: grey between views, black between rows
        colour = _BLACK if b % N == 0 else (190, 190, 190)
        draw.line([left, top + b * L * cell, left + side - 1, top + b * L * cell], fill=colour)
        draw.line([left + b * L * cell, top, left + b * L * cell, top + side - 1], fill=colour)
    draw.rectangle([left, top, left + side, top + side], outline=_BLACK)
    names = ("trunk", "rendering", "localization")
    for r in range(R):
        y = top + r * N * L * cell
        draw.text((8, y + N * L * cell / 2 - 7), names[r], fill=_BLACK, font=font)
        _centered(draw, names[r], left + r * N * L * cell, N * L * cell, top - 34, font)
        for i in range(N):
            draw.text((left - 22, y + i * L * cell + 9), f"v{i}", fill=_GREY, font=_font(11))
            draw.text((left + (r * N + i) * L * cell + 9, top - 16), f"v{i}", fill=_GREY, font=_font(11))
    draw.text((left + side / 2 - 70, top - 52), "keys (what is attended)", fill=_BLACK, font=font)
    draw.text((8, top - 34), "queries", fill=_BLACK, font=font)
    legend = (("trunk query attends", _TRUNK), ("rendering query attends", _GEN),
              ("localization query attends", _LOC), ("masked", _WHITE))
    for j, (label, colour) in enumerate(legend):
        y = top + 10 + 20 * j
        draw.rectangle([left + side + 14, y, left + side + 26, y + 12], fill=colour, outline=_GREY)
        draw.text((left + side + 32, y - 1), label, fill=_BLACK, font=_font(11))
    draw.text((left + side + 14, top + 100), "one cell: a query token", fill=_BLACK, font=_font(11))
    draw.text((left + side + 14, top + 114), "(row) and a key token", fill=_BLACK, font=_font(11))
    draw.text((left + side + 14, top + 128), "(column); v: view", fill=_BLACK, font=_font(11))
    return sheet


def loss_figure(ns):
    """Section 5: the toy run's losses, drawn by pyvf.train.curves.plot_curves (a run's curves.png)."""
    from pyvf.train.curves import plot_curves

    Image = _pil()[0]
    with tempfile.TemporaryDirectory() as run:
        with open(os.path.join(run, "log.csv"), "w") as f:
            f.write("step,loss,cross_entropy,pose_loss\n")
            for step, (loss, ce, pose) in enumerate(ns["history"]):
                f.write(f"{step},{loss!r},{ce!r},{pose!r}\n")
        png = plot_curves(run, os.path.join(run, "curves.png"), ["loss", "cross_entropy", "pose_loss"],
                          size=(300, 220), title="Section 5: a toy transformer (2 layers, width 32) on 8 "
                                                 "synthetic scenes: the loss before each of 30 AdamW steps")
        with Image.open(png) as img:
            return img.copy()


def render_figure(ns):
    """Section 6: context views, query views, their codebook reconstructions, pyvf's renderings."""
    Image, ImageDraw, _ = _pil()
    font, big = _font(12), _font(14)
    C, queries = ns["C"], ns["queries"]
    rows = [(f"context: views 0-{C - 1}", "given: tokens and poses", ns["images"][:C]),
            (f"truth: views {queries[0]}-{queries[-1]}", "the query views", ns["truth"]),
            ("codebook", "truth encoded + decoded", ns["recon"]),
            ("pyvf", "rendered from the context", ns["rendered"])]
    S, gap, left, top = 128, 6, 190, 34
    sheet = Image.new("RGB", (left + 5 * (S + gap), top + 4 * (S + gap) + 4), _WHITE)
    draw = ImageDraw.Draw(sheet)
    draw.text((10, 8), "Section 6: rendering with the shipped models (scene seed 7)", fill=_BLACK, font=big)
    for r, (name, note, tiles) in enumerate(rows):
        y = top + r * (S + gap)
        draw.text((10, y + S / 2 - 16), name, fill=_BLACK, font=font)
        draw.text((10, y + S / 2 + 2), note, fill=_GREY, font=_font(11))
        if r == 3:
            draw.text((10, y + S / 2 + 16), "and the query's pose", fill=_GREY, font=_font(11))
        for c, im in enumerate(tiles):
            sheet.paste(_tile(im, S // im.shape[0]), (left + c * (S + gap), y))
    return sheet


def pipeline_figure(ns):
    """Section 6 (shown at the top): pixels -> tokens -> transformer -> tokens -> a rendered view."""
    Image, ImageDraw, _ = _pil()
    font, small, big = _font(12), _font(11), _font(14)
    C, q0 = ns["C"], ns["queries"][0]
    images, tokens, rendered_tokens = ns["images"], ns["tokens"], ns["rendered_tokens"]
    t, gap, top = 64, 6, 52
    sheet = Image.new("RGB", (1030, top + C * (t + gap) + 40), _WHITE)
    draw = ImageDraw.Draw(sheet)
    draw.text((10, 8), f"The pipeline: {C} context views in, view {q0} rendered from its pose "
                       "(the shipped models, scene seed 7)", fill=_BLACK, font=big)
    x_img, x_tok, x_tf, x_out, x_dec = 20, 170, 320, 610, 800
    _centered(draw, "context pixels", x_img, t, top - 18, small)
    _centered(draw, "their 8x8 tokens", x_tok, t, top - 18, small)
    for i in range(C):
        y = top + i * (t + gap)
        sheet.paste(_tile(images[i], 1), (x_img, y))
        sheet.paste(_token_map(tokens[i], t // 8), (x_tok, y))
        _arrow(draw, (x_img + t + 6, y + t / 2), (x_tok - 8, y + t / 2), colour=_GREY)
        _arrow(draw, (x_tok + t + 6, y + t / 2), (x_tf - 8, top + C * (t + gap) / 2 - 10), colour=_GREY, width=1)
        draw.text((x_tok + t + 8, y + 2), f"+ c{i}", fill=_GREY, font=small)
    mid = top + C * (t + gap) / 2
    draw.text((x_img + t + 10, top + C * (t + gap) - 2), "encoder + nearest code (section 1)", fill=_BLACK, font=small)
    draw.rounded_rectangle([x_tf, mid - 70, x_tf + 170, mid + 50], radius=10, outline=_BLACK, width=2)
    for j, line in enumerate(("transformer", "trunk over the context,", "one rendering block", "for the query",
                              "(sections 2-4)")):
        _centered(draw, line, x_tf, 170, mid - 62 + 20 * j, font if j == 0 else small)
    draw.text((x_tf + 10, mid + 76), f"query pose c{q0}", fill=_GEN, font=font)
    _arrow(draw, (x_tf + 85, mid + 72), (x_tf + 85, mid + 54), colour=_GEN)
    _arrow(draw, (x_tf + 176, mid - 10), (x_out - 10, mid - 10))
    draw.text((x_tf + 182, mid - 42), "logits, then the", fill=_BLACK, font=small)
    draw.text((x_tf + 182, mid - 28), "most likely code", fill=_BLACK, font=small)
    S = 128
    sheet.paste(_token_map(rendered_tokens[0], S // 8), (x_out, int(mid - 10 - S / 2)))
    _centered(draw, f"view {q0}'s tokens", x_out, S, mid - 10 + S / 2 + 4, small)
    _arrow(draw, (x_out + S + 6, mid - 10), (x_dec - 8, mid - 10))
    draw.text((x_out + S + 10, mid - 28), "decoder", fill=_BLACK, font=small)
    sheet.paste(_tile(ns["rendered"][0], 2), (x_dec, int(mid - 10 - S / 2)))
    _centered(draw, f"rendered view {q0}", x_dec, S, mid - 10 + S / 2 + 4, small)
    sheet.paste(_tile(ns["truth"][0], 1), (x_dec + S + 20, int(mid - 10 - S / 2)))
    _centered(draw, "the truth", x_dec + S + 20, 64, mid - 10 - S / 2 + 68, small)
    return sheet


# name -> (the section whose namespace it is drawn from, the function)
FIGURES = {
    "walkthrough-pipeline.png": (6, pipeline_figure),
    "walkthrough-tokens.png": (1, tokens_figure),
    "walkthrough-ema.png": (1, ema_figure),
    "walkthrough-tree.png": (2, tree_figure),
    "walkthrough-mask.png": (2, mask_figure),
    "walkthrough-loss.png": (5, loss_figure),
    "walkthrough-render.png": (6, render_figure),
}


def draw_figures(runs, out):
    """Draw every picture of FIGURES into the folder `out` from run_sections()'s namespaces.
    Returns the paths written."""
    os.makedirs(out, exist_ok=True)
    spaces = {}
    for title, _, ns in runs:
        m = re.match(r"(\d+)\.", title)
        if m:
            spaces[int(m.group(1))] = ns
    paths = []
    for name, (section, draw) in FIGURES.items():
        path = os.path.join(out, name)
        draw(spaces[section]).save(path, format="PNG")
        paths.append(path)
    return paths


def main(argv=None):
    p = argparse.ArgumentParser(description="Run docs/walkthrough.md section by section and draw its pictures.")
    p.add_argument("--out", default=os.path.join(DOCS, "img"), help="folder for the pictures (default docs/img)")
    p.add_argument("--no-pictures", action="store_true", help="only run the examples")
    p.add_argument("-v", "--verbose", action="store_true", help="print every example as it runs")
    args = p.parse_args(argv)
    runs, seconds = run_sections(verbose=args.verbose)
    failed = sum(r.failed for _, r, _ in runs)
    attempted = sum(r.attempted for _, r, _ in runs)
    print(f"docs/walkthrough.md: {len(runs)} sections, {attempted} examples, {failed} failed, {seconds:.1f} s")
    if failed or not attempted:
        return 1
    if not args.no_pictures:
        print("wrote " + ", ".join(draw_figures(runs, args.out)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
