"""The codebook's vector quantizer (SPEC.md §4): the exact nearest-code lookup and the EMA quantizer.

    indices, sq_distances = vq_nearest(x, codes)    # x (M, D), codes (K, D)

    q = EMAQuantizer(embed_dim=D, n_embed=K, seed=0)
    out, cache = q.forward(z, train=True)           # z (B, D, h, w): out.quantized, out.codes, ...
    (dz,) = q.backward(dquantized, dcommitment, cache)

indices (M,) int64: for each row of x the index of the nearest code in squared Euclidean
distance, exactly (the argmin of sum_i (x_i - e_i)^2 computed in float64 from the given
values, ties to the smallest index), whatever the size of the vectors; sq_distances (M,) of
x's dtype: that distance, never negative. The C++ kernel (csrc/vq.cpp) scores codes by a fast
product and re-ranks exactly every code that its rounding-error bound cannot rule out.

Note the layouts: the published quantizer stores codes as the columns of
`quantize.embeddings` (embed_dim, n_embed); this function takes them as rows (K, D), i.e.
`embeddings.T` made contiguous.
"""

import dataclasses

import numpy as np

from . import _checks, _core

__all__ = ["vq_nearest", "EMAQuantizer", "QuantizerOutput"]


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


class EMAQuantizer:
    """The published EMA vector quantizer (SPEC.md §4).

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
        for name, val in (("embed_dim", embed_dim), ("n_embed", n_embed)):
            if isinstance(val, bool) or not isinstance(val, int) or val < 1:
                raise ValueError(f"{name} must be a positive integer, got {val!r}")
        if not 0.0 < decay < 1.0:
            raise ValueError(f"decay must be in (0, 1), got {decay}")
        if not eps > 0.0:
            raise ValueError(f"eps must be positive, got {eps}")
        if dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
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
        want = {"embeddings": (self.embed_dim, self.n_embed), "ema_cluster_size_hidden": (self.n_embed,),
                "ema_dw_hidden": (self.embed_dim, self.n_embed), "counter": ()}
        if set(state) != set(want):
            raise ValueError(f"quantizer state must have exactly {sorted(want)}, got {sorted(state)}")
        for name, shape in want.items():
            a = np.asarray(state[name])
            if a.shape != shape:
                raise ValueError(f"quantizer state {name!r} has shape {a.shape}, expected {shape}")
        self.embeddings = np.array(state["embeddings"], dtype=self.dtype)
        self.ema_cluster_size_hidden = np.array(state["ema_cluster_size_hidden"], dtype=self.dtype)
        self.ema_dw_hidden = np.array(state["ema_dw_hidden"], dtype=self.dtype)
        self.counter = int(state["counter"])

    def forward(self, z, train=False):
        """z (B, D, h, w) of the quantizer's dtype -> (QuantizerOutput, cache)."""
        if not isinstance(z, np.ndarray) or z.dtype != self.dtype:
            raise TypeError(f"z must be a {self.dtype} numpy array, got {getattr(z, 'dtype', type(z).__name__)}")
        if z.ndim != 4 or z.shape[1] != self.embed_dim:
            raise ValueError(f"z must have shape (B, {self.embed_dim}, h, w), got {z.shape}")
        if z.size == 0:
            raise ValueError(f"z is empty: shape {z.shape}")
        B, D, h, w = z.shape
        flat = np.ascontiguousarray(z.transpose(0, 2, 3, 1).reshape(-1, D))  # (M, D)
        idx, _ = vq_nearest(flat, np.ascontiguousarray(self.embeddings.T))  # codes are columns
        e = self.embeddings.T[idx]  # (M, D): the codes from before any update
        counts = np.bincount(idx, minlength=self.n_embed)  # (K,) N_k
        if train:
            self._ema_update(flat, idx, counts)
        diff = e - flat  # (M, D)
        commitment = float(np.mean(diff * diff))
        # straight-through: the published z + sg(e - z), whose value is e up to one rounding
        quantized = (flat + diff).reshape(B, h, w, D).transpose(0, 3, 1, 2)  # (B, D, h, w)
        p = counts[counts > 0] / counts.sum()
        out = QuantizerOutput(quantized=np.ascontiguousarray(quantized), codes=idx.reshape(B, h, w),
                              commitment_loss=commitment, usage=float((counts > 0).mean()),
                              perplexity=float(np.exp(-(p * np.log(p)).sum())))
        return out, (diff, z.shape)

    def backward(self, dquantized, dcommitment, cache):
        """dquantized (B, D, h, w), dcommitment (the loss's weight on the commitment loss) -> (dz,).
        Forward was quantized = z + sg(e - z) (identity for the gradient) and
        commitment = mean((sg(e) - z)^2), so dz = dquantized - dcommitment * 2 (e - z) / numel."""
        diff, shape = cache
        B, D, h, w = shape
        dflat = -2.0 * dcommitment / diff.size * diff  # (M, D)
        dz = dquantized + dflat.reshape(B, h, w, D).transpose(0, 3, 1, 2).astype(diff.dtype)
        return (dz,)

    def _ema_update(self, flat, idx, counts):
        K, dt = self.n_embed, self.dtype
        a = dt.type(1.0 - self.decay)
        S = np.zeros((self.embed_dim, K), dtype=dt)  # S_k: the sum of the vectors that chose k
        np.add.at(S.T, idx, flat)
        self.ema_cluster_size_hidden += a * (counts.astype(dt) - self.ema_cluster_size_hidden)
        self.ema_dw_hidden += a * (S - self.ema_dw_hidden)
        self.counter += 1
        debias = dt.type(1.0 - self.decay ** self.counter)
        cs = self.ema_cluster_size_hidden / debias  # (K,)
        dw = self.ema_dw_hidden / debias  # (D, K)
        n = cs.sum()
        cs = (cs + dt.type(self.eps)) / (n + K * dt.type(self.eps)) * n  # Laplace smoothing: > 0
        self.embeddings = dw / cs  # (D, K)

    def reset_dead_codes(self, z, threshold=1e-3, rng=None):
        """Optional (off unless called): codes whose smoothed cluster size is below threshold are
        moved to random vectors of z (B, D, h, w), their EMA statistics restarted there.
        Returns the number of codes reset."""
        rng = np.random.default_rng(rng)
        flat = z.transpose(0, 2, 3, 1).reshape(-1, self.embed_dim)
        debias = 1.0 - self.decay ** max(self.counter, 1)
        dead = np.flatnonzero(self.ema_cluster_size_hidden / debias < threshold)
        if dead.size:
            picks = flat[rng.integers(0, len(flat), dead.size)]  # (n_dead, D)
            # restart the statistics as if the code had been chosen once by its new vector:
            # bias-corrected cluster size 1 and dw = the vector, so dw / cs is the vector
            self.ema_cluster_size_hidden[dead] = debias
            self.ema_dw_hidden[:, dead] = picks.T * self.dtype.type(debias)
            self.embeddings[:, dead] = picks.T
        return int(dead.size)
