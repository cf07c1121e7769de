"""Unusual NumPy arrays given to pyvf's public array-taking functions: ndarray subclasses (masked
arrays, np.matrix), non-native byte order, misaligned memory, integer ids of any integer dtype.

Each test is a defect found that way (its docstring says what happened before) or a contract
the C++ kernels need (they read raw memory: native byte order, C order, any address). Oracles
are the same call on a plain, C-contiguous, native copy of the input, or the error contract of
pyvf._checks (every error names the argument and says why).
"""

import numpy as np
import pytest

import pyvf
from pyvf.models.codebook import Codebook, CodebookConfig
from pyvf.nn import conv, layers, losses

from conftest import assert_bitwise_equal

SMALL = dict(n_embeddings=16, n_head=2, d_model=8, n_layer=1, token_image_size=2, sequence_size=3, n_loss_skip=1)
TINY_CODEBOOK = dict(ch=32, ch_mult=(1,), num_res_blocks=1, attn_resolutions=(), z_channels=4, embed_dim=3,
                     n_embed=5, image_size=2)


def normal(rng, *shape, dtype=np.float32):
    return rng.standard_normal(shape).astype(dtype)


def unit_poses(rng, *shape, dtype=np.float64):
    p = rng.standard_normal(shape + (7,))
    p[..., 3:] /= np.linalg.norm(p[..., 3:], axis=-1, keepdims=True)
    return p.astype(dtype)


def masked(a, value):
    """a as a masked array whose first element is masked, the data under the mask set to `value`:
    a function that reads the data there computes with `value`."""
    m = np.ma.MaskedArray(a.copy(), mask=np.zeros(a.shape, bool))
    m.data.flat[0] = value
    m[np.unravel_index(0, a.shape)] = np.ma.masked
    return m


def misaligned(a):
    """A copy of a whose data starts one byte past an aligned address (flags.aligned is False)."""
    raw = np.zeros(a.nbytes + 1, np.uint8)
    out = raw[1:].view(a.dtype).reshape(a.shape)
    out[...] = a
    assert not out.flags.aligned and out.flags.c_contiguous
    return out


def transformer(dtype="float32", seed=0):
    return pyvf.Transformer(pyvf.TransformerConfig(**SMALL, dtype=dtype), seed=seed)


# ---------------------------------------------------------------------------------------
# the public calls, each with its arguments and which of them to replace (index, name)


def _cases(rng):
    q, k, v = (normal(rng, 2, 1, 1, 2, 3, 4) for _ in range(3))
    tm, cb = transformer(), Codebook(CodebookConfig(**TINY_CODEBOOK, dtype="float32"), seed=0)
    images = rng.uniform(-1, 1, (2, 3, 2, 2)).astype(np.float32)
    tokens = rng.integers(0, 16, (1, 3, 4))
    return {
        "branching_attention": (pyvf.branching_attention, [q, k, v], 0, "q"),
        "branching_attention_vjp": (pyvf.branching_attention_vjp, [q, k, v, normal(rng, *q.shape)], 3, "do"),
        "linear_forward": (lambda *a: layers.linear_forward(*a)[0],
                           [normal(rng, 3, 4), normal(rng, 4, 5), normal(rng, 1, 5)], 1, "w"),
        "conv2d_forward": (lambda *a: conv.conv2d_forward(*a, 1, 1)[0],
                           [normal(rng, 1, 2, 3, 3), normal(rng, 3, 2, 3, 3), normal(rng, 3)], 0, "x"),
        "cross_entropy_forward.targets": (lambda *a: losses.cross_entropy_forward(*a)[0],
                                          [normal(rng, 4, 5), rng.integers(0, 5, 4)], 1, "targets"),
        "embedding_forward.ids": (lambda *a: layers.embedding_forward(*a)[0],
                                  [rng.integers(0, 5, (2, 3)), normal(rng, 5, 4)], 0, "ids"),
        "sum_rows_by_id.ids": (lambda *a: layers.sum_rows_by_id(*a, 5),
                               [rng.integers(0, 5, 6), normal(rng, 6, 4)], 0, "ids"),
        "quat_rotate": (pyvf.quat_rotate, [unit_poses(rng, 3)[:, 3:].copy(), normal(rng, 3, 3, dtype=np.float64)],
                        1, "v"),
        "position_error": (pyvf.position_error, [unit_poses(rng, 3), unit_poses(rng, 3)], 0, "p1"),
        "Transformer.forward.poses": (lambda t, p: tm.forward(t, p).logits,
                                      [tokens, unit_poses(rng, 1, 3, dtype=np.float32)], 1, "poses"),
        "Codebook.encode": (cb.encode, [images], 0, "images"),
    }


CASES = list(_cases(np.random.default_rng(0)))


@pytest.fixture(scope="module")
def cases():
    return _cases(np.random.default_rng(0))


# ---------------------------------------------------------------------------------------
# masked arrays


@pytest.mark.parametrize("case", CASES)
def test_masked_values_are_refused(cases, case):
    """A masked array is an ndarray, so every check passed it and the kernels (and NumPy's index
    and reduction paths) computed with the data under the mask: branching_attention with a masked
    q element set to 1e3, sum_rows_by_id with a masked id, ... returned an answer silently (the
    masked value used: sum_rows_by_id's rows went to the wrong sums, max |diff| 2.2). Now a
    TypeError names the argument and says it has masked values."""
    fn, args, i, name = cases[case]
    a = args[i]
    args = list(args)
    args[i] = masked(a, 1e3 if a.dtype.kind == "f" else 4)
    with pytest.raises(TypeError, match=rf"^{name} .*masked"):
        fn(*args)


@pytest.mark.parametrize("case", ["branching_attention", "conv2d_forward", "sum_rows_by_id.ids", "position_error"])
def test_masked_array_with_nothing_masked_is_its_data(cases, case):
    """A masked array whose mask is all False holds ordinary values: the answer is the plain
    array's (the refusal above is of masked values, not of the class)."""
    fn, args, i, _ = cases[case]
    want = fn(*args)
    args = list(args)
    args[i] = np.ma.MaskedArray(args[i].copy(), mask=np.zeros(args[i].shape, bool))
    assert_bitwise_equal(case, np.ma.getdata(fn(*args)), want)


def test_masked_checkpoint_entry_is_refused():
    """load_official read a masked entry's data (np.array drops the mask): the masked 1e30 became
    wte/weight[0, 0] silently. Now the entry is named as a problem and nothing is loaded."""
    sd = transformer(seed=0).state_dict()
    m = transformer(seed=1)
    before = m.state_dict()
    with pytest.raises(TypeError, match=r"'wte/weight'.*masked"):
        m.load_official({**sd, "wte/weight": masked(sd["wte/weight"], 1e30)})
    for name, a in m.state_dict().items():
        assert_bitwise_equal(name, a, before[name])


# ---------------------------------------------------------------------------------------
# np.matrix: its operators and indexing are not an ndarray's


@pytest.mark.filterwarnings("ignore::PendingDeprecationWarning")  # np.matrix's own
def test_matrix_is_refused(rng):
    """np.matrix stays 2-D under indexing and reductions: quat_mul(a, np.asmatrix(b)) returned a
    (1, 4) array for three quaternions (3, 4), position_error(np.asmatrix(p1), p2) a (3, 1) array
    instead of (3,), other calls failed deep inside with "matrix.max() got an unexpected keyword
    argument 'keepdims'" or a pyvf._core bias-shape error. Now a TypeError names the argument."""
    a, b = unit_poses(rng, 3)[:, 3:].copy(), unit_poses(rng, 3)[:, 3:].copy()
    with pytest.raises(TypeError, match=r"^b is a numpy.matrix"):
        pyvf.quat_mul(a, np.asmatrix(b))
    p1, p2 = unit_poses(rng, 3), unit_poses(rng, 3)
    with pytest.raises(TypeError, match=r"^p1 is a numpy.matrix"):
        pyvf.position_error(np.asmatrix(p1), p2)
    x, w, bias = normal(rng, 3, 4), normal(rng, 4, 5), normal(rng, 1, 5)
    with pytest.raises(TypeError, match=r"^b is a numpy.matrix"):
        layers.linear_forward(x, w, np.asmatrix(bias))


# ---------------------------------------------------------------------------------------
# byte order


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_non_native_byte_order_is_refused_saying_so(rng, dtype):
    """A big-endian float32 is not what the kernels read (they take the bytes as they are), so it
    is refused; the message said "q must be float32 or float64, got >f4" of an array that is
    float32. It now says the byte order is the problem, and its remedy gives the plain answer."""
    q, k, v = (normal(rng, 2, 1, 1, 2, 3, 4, dtype=dtype) for _ in range(3))
    qb = q.astype(q.dtype.newbyteorder(">"))
    with pytest.raises(TypeError, match=r"^q .*byte order"):
        pyvf.branching_attention(qb, k, v)
    assert_bitwise_equal("o", pyvf.branching_attention(qb.astype(qb.dtype.newbyteorder("=")), k, v),
                         pyvf.branching_attention(q, k, v))


def test_big_endian_checkpoint_loads_its_values():
    """A checkpoint of big-endian floats (an .npz written on a big-endian machine, or with
    dtype '>f4') was refused: "'wte/weight' has dtype >f4, expected a float array (float32 or
    float64)". Its values are exactly representable natively (the loader copies every entry to
    the model's dtype anyway): the loaded model is the native checkpoint's, bitwise."""
    sd = transformer(seed=0).state_dict()
    m = transformer(seed=1)
    m.load_official({k: a.astype(a.dtype.newbyteorder(">")) for k, a in sd.items()})
    for name, a in m.state_dict().items():
        assert a.dtype == np.float32 and a.dtype.isnative
        assert_bitwise_equal(name, a, sd[name])


@pytest.mark.parametrize("ids_dtype", ["uint64", "int8", ">i8", ">i4", "uint8"])
def test_integer_targets_of_any_integer_dtype(rng, ids_dtype):
    """The cross-entropy's targets reach a C++ kernel, which reads native int64: targets of any
    integer dtype (unsigned, narrow, big-endian) give the int64 targets' loss, bitwise."""
    logits, t = normal(rng, 6, 5), rng.integers(0, 5, 6)
    want = losses.cross_entropy_forward(logits, t)[0]
    assert_bitwise_equal(ids_dtype, losses.cross_entropy_forward(logits, t.astype(ids_dtype))[0], want)


# ---------------------------------------------------------------------------------------
# memory the kernels read as it is


@pytest.mark.parametrize("path", pyvf.kernel_paths())
def test_misaligned_inputs_give_the_aligned_answer(rng, path):
    """The kernels take raw pointers; a misaligned float array (np.frombuffer at an odd offset)
    is C-contiguous and passes every check. Its answer must be the aligned copy's, bitwise, on
    every instruction-set path (vector loads are unaligned ones), never a crash."""
    q, k, v = (normal(rng, 2, 1, 2, 3, 5, 9, dtype=np.float64) for _ in range(3))
    x, w, b = normal(rng, 7, 33), normal(rng, 33, 17), normal(rng, 1, 17)
    img, kw, kb = normal(rng, 2, 3, 5, 5), normal(rng, 4, 3, 3, 3), normal(rng, 4)
    with pyvf.use_kernel_path(path):
        assert_bitwise_equal("o", pyvf.branching_attention(*map(misaligned, (q, k, v))),
                             pyvf.branching_attention(q, k, v))
        assert_bitwise_equal("y", layers.linear_forward(*map(misaligned, (x, w, b)))[0],
                             layers.linear_forward(x, w, b)[0])
        assert_bitwise_equal("conv", conv.conv2d_forward(*map(misaligned, (img, kw, kb)), 1, 1)[0],
                             conv.conv2d_forward(img, kw, kb, 1, 1)[0])


def test_use_kernel_path_object_used_twice_switches_each_time():
    """`ctx = use_kernel_path("baseline")` entered a second time after its exit ran the block on
    the path the process was on (avx512 here), because the switch happened only when the object was
    made. Each `with` switches, and each exit puts back the path from before it."""
    start = pyvf.kernel_path()
    # another path than the current one (x86-64 always has baseline beside avx2/avx512; a machine
    # with one path only cannot tell the two apart)
    other = next((p for p in pyvf.kernel_paths() if p != start), start)
    ctx = pyvf.use_kernel_path(other)
    for _ in range(2):
        with ctx:
            assert pyvf.kernel_path() == other
        assert pyvf.kernel_path() == start


def test_masked_codes_tokens_and_pictures_are_refused_naming_them():
    """The entries that check their integer or uint8 arrays themselves: decode_code decoded masked
    codes from the data under the mask (0.27 off), a transformer's masked tokens were refused
    naming the embedding's "ids", and the metrics scored masked pixels (to_model_images 170 off)."""
    from pyvf.evaluate import metrics
    cb = Codebook(CodebookConfig(**TINY_CODEBOOK, dtype="float32"), seed=0)
    with pytest.raises(TypeError, match="^codes is a masked array with masked elements"):
        cb.decode_code(masked(np.zeros((1, 2, 2), np.int64), 3))
    tm, rng = transformer(), np.random.default_rng(0)
    with pytest.raises(TypeError, match="^tokens is a masked array with masked elements"):
        tm.forward(masked(rng.integers(0, 16, (1, 3, 4)), 3), unit_poses(rng, 1, 3, dtype=np.float32))
    with pytest.raises(TypeError, match="^images is a masked array with masked elements"):
        metrics.to_model_images(masked(np.zeros((1, 4, 4, 3), np.uint8), 255), np.float32)
    with pytest.raises(TypeError, match="^x is a masked array with masked elements"):
        metrics.to_uint8(masked(np.zeros((1, 3, 4, 4)), 1.0))
