"""Compare a port's activations (or gradients) with pyvf's, name by name: where does it go wrong?

    out = model.forward(tokens, poses, trace=True)       # pyvf: name -> activation, execution order
    report = pyvf.compare(my_trace, out.trace)           # yours first, the reference second
    report.first                                         # e.g. "blocks.1.attn.q" (None: all agree)

Both sides map names to arrays (or torch tensors, read through .detach()). The walk follows
`ref`'s order (pyvf's trace: execution order; backward()'s dict: backward order), so the first
quantity over tolerance is where a bug starts. The error is normwise, rel_err = max|x - ref| /
max|ref| in float64: an elementwise relative error is meaningless where ref is near zero.

Default tolerances (DEFAULT_RTOL) follow the dtype of the less precise side (or `dtype=`), a
few orders above rounding and below what a wrong layer gives; docs/verify.md (Tolerances) says
why. Integer and boolean arrays (token ids) must match exactly.
"""

import dataclasses

import numpy as np

from .. import _checks

__all__ = ["compare", "Comparison", "ComparisonRow", "DEFAULT_RTOL", "rel_err"]

DEFAULT_RTOL = {"float64": 1e-10, "float32": 1e-3, "float16": 2e-2, "bfloat16": 5e-2}
_PRECISION = ("float64", "float32", "float16", "bfloat16")  # most precise first


def rel_err(x, ref):
    """max |x - ref| / max |ref| in float64, both scaled by one power of two first so that x - ref
    does not overflow (rel_err([1e308], [-1e308]) is 2). 0 for empty arrays; max |x| where ref is
    all zero."""
    x, ref = np.asarray(x, dtype=np.float64), np.asarray(ref, dtype=np.float64)
    if x.shape != ref.shape:
        raise ValueError(f"shapes differ: {x.shape} vs {ref.shape}")
    if x.size == 0:
        return 0.0
    top, k = max(np.abs(x).max(), np.abs(ref).max()), 0
    if np.isfinite(top) and top > 0:  # (a NaN or inf in x is reported as such below)
        k = int(np.frexp(top)[1])
        x, ref = np.ldexp(x, -k), np.ldexp(ref, -k)
    scale = np.abs(ref).max()
    if scale == 0:  # ref all zero: the absolute error (divided by 1), scaled back
        return float(np.ldexp(np.abs(x).max(), k))
    return float(np.abs(x - ref).max() / scale)


@dataclasses.dataclass
class ComparisonRow:
    name: str
    shape: tuple  # ref's shape
    dtype: str  # the dtype the tolerance was taken from
    max_abs: float  # max |mine - ref| (inf when the shapes differ)
    rel: float  # max |mine - ref| / max |ref| (inf when the shapes differ, nan when mine is not finite)
    rtol: float
    note: str = ""  # e.g. the shapes, when they differ
    atol: float = 0.0  # an absolute error always accepted (compare's atol=)

    @property
    def ok(self):
        return bool(self.rel <= self.rtol or self.max_abs <= self.atol)  # False for nan


@dataclasses.dataclass
class Comparison:
    first: str  # the first name (in ref's order) over tolerance; None when none is
    rows: list  # ComparisonRow per name present on both sides, in ref's order
    only_mine: list  # names in mine but not in ref (mine's order)
    only_ref: list  # names in ref but not in mine (ref's order)

    @property
    def ok(self):
        """Every shared quantity within tolerance and no name on one side only."""
        return self.first is None and not self.only_mine and not self.only_ref

    def table(self):
        """Markdown table: every shared quantity's max abs and normwise relative error."""
        lines = ["| # | name | shape | dtype | max abs err | rel err | rtol | |",
                 "|---|---|---|---|---|---|---|---|"]
        for i, r in enumerate(self.rows):
            mark = "FIRST" if r.name == self.first else ("ok" if r.ok else "over")
            note = f" {r.note}" if r.note else ""
            lines.append(f"| {i} | {r.name} | {r.shape} | {r.dtype} | {r.max_abs:.3e} | {r.rel:.3e} "
                         f"| {r.rtol:.0e} | {mark}{note} |")
        return "\n".join(lines)

    def __str__(self):
        if self.first is None:
            head = f"all {len(self.rows)} shared quantities within tolerance"
        else:
            r = next(r for r in self.rows if r.name == self.first)
            n_over = sum(not r.ok for r in self.rows)
            head = (f"first divergence: {r.name}: relative error {r.rel:.3e} > rtol {r.rtol:.0e} "
                    f"({r.dtype}){' ' + r.note if r.note else ''}; {n_over} of {len(self.rows)} over tolerance")
        parts = [head, "", self.table()]
        if self.only_mine:
            parts += ["", f"only in mine ({len(self.only_mine)}): {', '.join(self.only_mine)}"]
        if self.only_ref:
            parts += ["", f"only in ref ({len(self.only_ref)}): {', '.join(self.only_ref)}"]
        return "\n".join(parts)


def _to_numpy(name, side, x):
    """-> (ndarray, dtype name). torch tensors through .detach().cpu(); bfloat16 (which numpy
    lacks) widened to float32 exactly, its name kept for the tolerance."""
    if hasattr(x, "detach"):
        x = x.detach().cpu()
        if str(x.dtype) == "torch.bfloat16":
            return x.float().numpy(), "bfloat16"
        x = x.numpy()
    a = np.asarray(x)
    if a.dtype.kind not in "fiub":
        raise TypeError(f"compare: {side}[{name!r}] must be a real numeric array, got dtype {a.dtype}")
    return a, a.dtype.name


def _tolerance(dt_mine, dt_ref, dtype, rtol):
    """(dtype name the tolerance follows, rtol). An integer or boolean ref (token ids, codes)
    must match exactly, whatever mine's dtype or `dtype` (one wrong code of 1024 is a normwise
    error under float32's rtol); only an explicit rtol overrides that."""
    if rtol is None and dt_ref != "bfloat16" and np.dtype(dt_ref).kind in "iub":
        return dt_ref, 0.0
    if dtype is not None:
        dt = str(np.dtype(dtype)) if str(dtype) != "bfloat16" else "bfloat16"
    else:
        floats = [d for d in (dt_mine, dt_ref) if d in _PRECISION]
        dt = max(floats, key=_PRECISION.index) if floats else dt_ref  # the less precise side
    if rtol is not None:
        return dt, rtol
    return dt, DEFAULT_RTOL.get(dt, 0.0)  # integers: exactly


def compare(mine, ref, *, dtype=None, rtol=None, atol=0.0):
    """Compare two mappings name -> array, walking ref's order -> Comparison (.first, .rows, .ok;
    str() is the report). dtype: whose default tolerance applies (default: the less precise
    side's); rtol: one normwise tolerance for every quantity. atol: an absolute error accepted
    whatever the relative one, for quantities zero in exact arithmetic (a conv bias feeding a
    GroupNorm of one channel per group), e.g. 1e-10 * max|ref gradient|."""
    if rtol is not None:
        rtol = _checks.real("rtol", rtol, lo=0.0)
    atol = _checks.real("atol", atol, lo=0.0)
    if dtype is not None and str(dtype) != "bfloat16" and np.dtype(dtype).name not in DEFAULT_RTOL:
        raise ValueError(f"compare: dtype must be one of {list(DEFAULT_RTOL)}, got {dtype!r}")
    rows, first = [], None
    for name, r in ref.items():
        if name not in mine:
            continue
        a, dt_a = _to_numpy(name, "mine", mine[name])
        b, dt_b = _to_numpy(name, "ref", ref[name])
        dt, tol = _tolerance(dt_a, dt_b, dtype, rtol)
        if a.shape != b.shape:
            row = ComparisonRow(name, b.shape, dt, np.inf, np.inf, tol, f"(shape {a.shape} vs ref {b.shape})")
        elif a.size == 0:
            row = ComparisonRow(name, b.shape, dt, 0.0, 0.0, tol, atol=atol)
        else:
            with np.errstate(invalid="ignore", over="ignore"):
                max_abs = float(np.abs(a.astype(np.float64) - b.astype(np.float64)).max())
                rel = rel_err(a, b)
            if not np.isfinite(b.astype(np.float64)).all():
                row = ComparisonRow(name, b.shape, dt, max_abs, np.nan, tol, "(ref not finite)")
            else:
                row = ComparisonRow(name, b.shape, dt, max_abs, rel, tol,
                                    "" if np.isfinite(rel) else "(mine not finite)", atol=atol)
                if not rel <= tol and row.ok:
                    row.note = f"(max abs err within atol {atol:.1e})"
        rows.append(row)
        if first is None and not row.ok:
            first = name
    only_mine = [n for n in mine if n not in ref]
    only_ref = [n for n in ref if n not in mine]
    return Comparison(first=first, rows=rows, only_mine=only_mine, only_ref=only_ref)
