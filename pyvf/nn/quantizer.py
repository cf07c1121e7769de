"""The codebook's vector quantizer (docs/math.md §4): the exact nearest-code lookup and the EMA quantizer.

    indices, sq_distances = vq_nearest(x, codes)    # x (M, D), codes (K, D): codes as rows
    q = EMAQuantizer(embed_dim=D, n_embed=K, seed=0)
    out, cache = q.forward(z, train=True)           # z (B, D, h, w): out.quantized, out.codes, ...
    (dz,) = q.backward(dquantized, dcommitment, cache)

vq_nearest: each row's nearest code in squared Euclidean distance, exactly (the argmin in
float64 of the given values, ties to the smallest index), and that distance; the C++ kernel
(csrc/vq.cpp) re-ranks exactly every code its fast product's error bound cannot rule out. The
published quantizer stores codes as the COLUMNS of `quantize.embeddings` (D, K).
"""

import dataclasses

import numpy as np

from .. import _checks, _core
from .layers import sum_rows_by_id

__all__ = ["vq_nearest", "code_statistics", "code_utility", "low_utility_codes", "EMAQuantizer", "QuantizerOutput"]


def _check_2d(name, a, like=None):
    """a: a finite C-contiguous float (M, D) array (of like's dtype and width, when given)."""
    _checks.float_array(name, a, like, "x")
    if a.ndim != 2:
        raise ValueError(f"{name} must be 2-dimensional, got shape {a.shape}")
    if like is not None and a.shape[1] != like.shape[1]:
        raise ValueError(f"{name} has width {a.shape[1]} but x has width {like.shape[1]}")
    _checks.contiguous(name, a)
    _checks.finite(name, a)


def vq_nearest(x, codes):
    """x (M, D), codes (K, D), one float dtype -> indices (M,) int64, sq_distances (M,)."""
    _check_2d("x", x)
    _check_2d("codes", codes, like=x)
    if codes.shape[0] == 0:
        raise ValueError("codes is empty: there is no nearest code")
    if x.shape[1] == 0:
        raise ValueError("x and codes have width 0")
    index = np.empty(x.shape[0], dtype=np.int64)
    sq = np.empty(x.shape[0], dtype=x.dtype)
    if x.shape[0]:
        _core.vq_nearest(index, sq, x, codes)
    return index, sq


@dataclasses.dataclass
class QuantizerOutput:
    quantized: np.ndarray  # (B, D, h, w) straight-through output z + sg(e - z): the value of e
    codes: np.ndarray  # (B, h, w) int64
    commitment_loss: float  # mean((sg(e) - z)^2)
    usage: float  # fraction of the n_embed codes used by this batch
    perplexity: float  # exp(entropy of the batch's code frequencies): n_embed when all are used evenly


def code_statistics(counts):
    """counts (K,): how often each code was chosen -> (usage: the fraction of codes used,
    perplexity: exp of the entropy of the code frequencies, K when all are used evenly)."""
    p = counts[counts > 0] / counts.sum()
    return float((counts > 0).mean()), float(np.exp(-(p * np.log(p)).sum()))


class EMAQuantizer:
    """The published EMA vector quantizer (docs/math.md §4).

    Buffers (the published names): `embeddings` (embed_dim, n_embed), the codes as COLUMNS,
    initialised uniform in (-sqrt 3, sqrt 3); `ema_cluster_size_hidden` (n_embed,),
    `ema_dw_hidden` (embed_dim, n_embed), `counter` (the number of EMA updates).

    A training step (train=True), with N_k the number of vectors that chose code k and S_k their sum:
        hidden_cs += (1 - decay) (N - hidden_cs);  hidden_dw += (1 - decay) (S - hidden_dw);  counter += 1
        cs = hidden_cs / (1 - decay^counter);      dw = hidden_dw / (1 - decay^counter)   (bias correction)
        n = sum(cs);  cs' = (cs + eps) / (n + n_embed eps) * n                           (Laplace smoothing)
        embeddings = dw / cs'
    The output uses the codes from BEFORE the update. A code no vector chose keeps decaying
    towards 0 (its dw does); cs' > 0 always, so no NaN even when a code, or all but one, is unused.
    """

    def __init__(self, embed_dim, n_embed, decay=0.99, eps=1e-5, dtype="float32", seed=0):
        self.embed_dim, self.n_embed, self.decay, self.eps = embed_dim, n_embed, decay, eps
        self.dtype = np.dtype(dtype)
        rng = np.random.default_rng(seed)
        lim = np.sqrt(3.0)
        self.embeddings = rng.uniform(-lim, lim, (embed_dim, n_embed)).astype(self.dtype)
        self.ema_cluster_size_hidden = np.zeros(n_embed, self.dtype)
        self.ema_dw_hidden = np.zeros((embed_dim, n_embed), self.dtype)
        self.counter = 0

    def state_dict(self):
        return {"embeddings": self.embeddings.copy(), "ema_cluster_size_hidden": self.ema_cluster_size_hidden.copy(),
                "ema_dw_hidden": self.ema_dw_hidden.copy(), "counter": np.array(self.counter, np.int64)}

    def load_state_dict(self, state):
        """Restore a state_dict() (copies; checked where a file enters: Codebook.load_official)."""
        self.embeddings = np.array(state["embeddings"], self.dtype)
        self.ema_cluster_size_hidden = np.array(state["ema_cluster_size_hidden"], self.dtype)
        self.ema_dw_hidden = np.array(state["ema_dw_hidden"], self.dtype)
        self.counter = int(state["counter"])

    def forward(self, z, train=False, empty=None):
        """z (B, D, h, w) -> (QuantizerOutput, cache). train=True applies one EMA update (the
        output uses the codes from before it). empty: None (published), or bool (B, h, w): the
        empty positions take code 0, the others their nearest of the rest."""
        B, D, h, w = z.shape
        empty = None if empty is None else empty.reshape(-1)  # (M,)
        flat = np.ascontiguousarray(z.transpose(0, 2, 3, 1).reshape(-1, D))  # (M, D)
        codes = np.ascontiguousarray(self.embeddings.T)  # (K, D): the codes are columns
        if empty is None:
            idx = vq_nearest(flat, codes)[0]  # (M,)
        else:  # code 0 is the empty code: the empty vectors take it, the others their nearest of 1..K-1
            idx = np.zeros(len(flat), np.int64)
            if not empty.all():
                idx[~empty] = vq_nearest(np.ascontiguousarray(flat[~empty]), codes[1:])[0] + 1
        e = self.embeddings.T[idx]  # (M, D): the codes from before any update (a copy)
        counts = np.bincount(idx, minlength=self.n_embed)  # (K,) N_k
        diff = e - flat  # (M, D)
        # summed in float64: a float32 sum overflows where the mean of finite squares does not
        commitment = float(np.mean(diff * diff, dtype=np.float64))
        # straight-through: the published z + sg(e - z), whose value is e up to one rounding
        quantized = (flat + diff).reshape(B, h, w, D).transpose(0, 3, 1, 2)  # (B, D, h, w)
        if train:
            self._ema_update(flat, idx, counts)
        usage, perplexity = code_statistics(counts)
        out = QuantizerOutput(quantized=np.ascontiguousarray(quantized), codes=idx.reshape(B, h, w),
                              commitment_loss=commitment, usage=usage, perplexity=perplexity)
        return out, (diff, z.shape)

    def backward(self, dquantized, dcommitment, cache):
        """dquantized (B, D, h, w), dcommitment (the loss's weight on the commitment loss) -> (dz,).
        Forward was quantized = z + sg(e - z) (identity for the gradient) and
        commitment = mean((sg(e) - z)^2), so dz = dquantized - dcommitment * 2 (e - z) / numel."""
        diff, (B, D, h, w) = cache
        dflat = -2.0 * dcommitment / diff.size * diff  # (M, D)
        return (dquantized + dflat.reshape(B, h, w, D).transpose(0, 3, 1, 2).astype(diff.dtype),)

    def _ema_update(self, flat, idx, counts):
        """One EMA update of the buffers (the class docstring's formulas)."""
        K, dt = self.n_embed, self.dtype
        a = dt.type(1.0 - self.decay)
        S = sum_rows_by_id(idx, flat, K).T  # (D, K), S_k: the sum of the vectors that chose k
        hcs, hdw = self.ema_cluster_size_hidden, self.ema_dw_hidden
        self.ema_cluster_size_hidden = hcs + a * (counts.astype(dt) - hcs)  # (K,)
        self.ema_dw_hidden = hdw + a * (S - hdw)  # (D, K)
        self.counter += 1
        debias = dt.type(1.0 - self.decay ** self.counter)
        cs = self.ema_cluster_size_hidden / debias  # (K,)
        dw = self.ema_dw_hidden / debias  # (D, K)
        n = cs.sum()
        cs = (cs + dt.type(self.eps)) / (n + K * dt.type(self.eps)) * n  # Laplace smoothing: > 0
        self.embeddings = dw / cs  # (D, K)

    def reset_dead_codes(self, z, threshold=1e-3, rng=None, restart="batch", reseat=0, empty=None):
        """Move the codes whose smoothed cluster size is below threshold to vectors of z (B, D, h, w),
        distinct while there are enough, their EMA statistics restarted there -> the number moved.
        restart: "batch", vectors drawn uniformly; "worst", the worst-represented first. reseat:
        also move up to this many live codes of least utility (low_utility_codes) to the worst-
        represented vectors left, while it lowers the batch's error (ELBG, Patane and Russo 2001).
        empty: as forward's; code 0 never moves, the others only to non-empty positions' vectors."""
        rng = np.random.default_rng(rng)
        empty = None if empty is None else empty.reshape(-1)  # (M,)
        flat = z.transpose(0, 2, 3, 1).reshape(-1, self.embed_dim)  # (M, D)
        first = 0 if empty is None else 1  # the codes before `first` never move
        if empty is not None:
            flat = flat[~empty]  # (M', D): the vectors the other codes stand for
        M = len(flat)
        if M == 0:
            return 0
        debias = 1.0 - self.decay ** max(self.counter, 1)
        dead = np.flatnonzero(self.ema_cluster_size_hidden[first:] / debias < threshold)  # indices from `first`
        if restart == "batch":
            # distinct vectors while there are enough (two codes on one vector: the larger index is
            # never chosen, ties go to the smallest), then vectors drawn again for the rest
            pick = np.concatenate([rng.permutation(M), rng.integers(0, M, max(dead.size - M, 0))])[:dead.size]
        if restart == "worst" or reseat:
            codes = np.ascontiguousarray(self.embeddings.T[first:])  # (K - first, D)
            idx, util, second = code_utility(flat, codes)
            err = ((flat.astype(np.float64) - codes[idx]) ** 2).sum(axis=1)  # (M,)
            worst = np.argsort(-err, kind="stable")  # (M,) worst represented first
            if restart == "worst":
                pick = np.resize(worst, dead.size)  # distinct while M >= the dead codes
            taken = dead.size if restart == "worst" else 0
            low = low_utility_codes(idx, util, second, dead, err[worst[taken:taken + reseat]])
            moved, pick = np.concatenate([dead, low]), np.concatenate([pick, worst[taken:taken + low.size]])
        else:
            moved = dead
        moved = moved + first
        if moved.size:
            picks = flat[pick]  # (n_moved, D)
            # restart the statistics as if the code had been chosen once by its new vector:
            # bias-corrected cluster size 1 and dw = the vector, so dw / cs is the vector
            self.ema_cluster_size_hidden[moved] = debias
            self.ema_dw_hidden[:, moved] = picks.T * self.dtype.type(debias)
            self.embeddings[:, moved] = picks.T
        return int(moved.size)

    def init_kmeans(self, z, iters, batch, rng=None, empty=None):
        """Codes from data: k-means++ seeding on the vectors of z (B, D, h, w), then `iters` Lloyd
        iterations; the EMA statistics set as if one update (counter 1) had seen each code chosen
        by its cluster's share of a batch of `batch` images. empty: as forward's; code 0 then
        starts at the mean of the empty positions' vectors."""
        flat = np.ascontiguousarray(z.transpose(0, 2, 3, 1).reshape(-1, self.embed_dim), np.float64)  # (M, D)
        scale = batch / z.shape[0]  # images per batch / images in z
        empty = None if empty is None else empty.reshape(-1)  # (M,)
        if empty is not None:
            e0, n0 = (flat[empty].mean(axis=0), empty.sum() * scale) if empty.any() else (self.embeddings[:, 0], 0.0)
            flat = flat[~empty]
        rng = np.random.default_rng(rng)
        K, M = self.n_embed - (empty is not None), len(flat)
        c = np.empty((K, self.embed_dim))  # (K, D)
        c[0] = flat[rng.integers(M)]
        d = ((flat - c[0]) ** 2).sum(axis=1)  # (M,) squared distance to the nearest chosen centre
        for k in range(1, K):  # D^2 sampling: a cluster of identical vectors is seeded once
            c[k] = flat[rng.choice(M, p=d / d.sum())] if d.sum() > 0 else flat[rng.integers(M)]
            d = np.minimum(d, ((flat - c[k]) ** 2).sum(axis=1))
        for _ in range(iters):
            idx, _ = vq_nearest(flat, c)
            n = np.bincount(idx, minlength=K)  # (K,)
            c[n > 0] = (sum_rows_by_id(idx, flat, K) / np.maximum(n, 1)[:, None])[n > 0]
        idx, _ = vq_nearest(flat, c)
        n = np.bincount(idx, minlength=K) * scale  # (K,) chosen per batch
        if empty is not None:  # code 0 first
            c, n = np.vstack([e0, c]), np.concatenate([[n0], n])
        a = 1.0 - self.decay  # hidden = a * (bias-corrected value) at counter 1
        self.embeddings = np.ascontiguousarray(c.T.astype(self.dtype))  # (D, K)
        self.ema_cluster_size_hidden = (a * n).astype(self.dtype)
        self.ema_dw_hidden = (a * c.T * n).astype(self.dtype)
        self.counter = 1


def code_utility(x, codes):
    """x (M, D), codes (K, D) -> (idx (M,): each vector's nearest code, utility (K,) float64: the
    increase of the total squared error sum_m |x_m - codes[idx_m]|^2 were code k removed and its
    vectors sent to their second-nearest code (inf for a single code), second (M,): that code).
    0 for a code no vector chose, about 0 for codes that split one tight cluster. In float64."""
    x, c = x.astype(np.float64), codes.astype(np.float64)
    d = (x * x).sum(1)[:, None] - 2.0 * x @ c.T + (c * c).sum(1)  # (M, K) squared distances
    rows = np.arange(len(x))
    idx = np.argmin(d, axis=1)  # (M,)
    d1 = d[rows, idx].copy()
    d[rows, idx] = np.inf
    second = np.argmin(d, axis=1)  # (M,)
    return idx, np.bincount(idx, d[rows, second] - d1, minlength=len(c)), second


def low_utility_codes(idx, util, second, exclude, gains):
    """The codes to move, least utility first (ties to the smaller index), at most len(gains):
    the i-th only while its utility is below gains[i] (the squared error of the vector it goes
    to), among codes some vector chose, not in exclude, not the second-nearest code of a chosen
    code's vectors (they take those vectors) and whose own vectors' second-nearest codes stay."""
    K = len(util)
    blocked = np.bincount(idx, minlength=K) == 0  # (K,) a code absent from the batch is not judged
    blocked[exclude] = True
    chosen = []
    for k in np.argsort(util, kind="stable"):
        if len(chosen) == len(gains) or util[k] >= gains[len(chosen)]:
            break
        takers = second[idx == k]
        if blocked[k] or np.isin(takers, chosen).any():
            continue
        chosen.append(k)
        blocked[takers] = True
    return np.array(chosen, dtype=np.int64)
