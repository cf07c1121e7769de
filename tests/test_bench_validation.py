"""Every benchmark validates what it times before timing it (pyvf/bench/__init__.py): a bug planted
in a timed computation (a NaN gradient, a transposed mask or weight, a dropped output, zeros)
must stop it, or record a failure, instead of printing a time. Each test plants one such bug in
one benchmark and runs the part that validates, on tiny inputs (about 30 s in all on 2 cores).
"""

import numpy as np
import pytest
import torch

import pyvf
from pyvf.bench import accuracy, attention, codebook, common, scaling, transformer, vq


@pytest.fixture(autouse=True)
def _keep_threads():
    """The benchmarks set pyvf's and torch's threads: put them back for the other tests."""
    n, nt = pyvf.num_threads(), torch.get_num_threads()
    yield
    pyvf.set_num_threads(n)
    torch.set_num_threads(nt)


def _nan_dq(monkeypatch):
    """pyvf's attention backward with a NaN in dq (the other gradients right)."""
    backward = pyvf.branching_attention_backward

    def planted(*args, **kwargs):
        dq, dk, dv = backward(*args, **kwargs)
        dq = dq.copy()
        dq.flat[0] = np.nan
        return dq, dk, dv
    monkeypatch.setattr(pyvf, "branching_attention_backward", planted)


# ---------------------------------------------------------------------------------------
# attention


def test_attention_demo_fails_on_a_nan_gradient(monkeypatch, capsys):
    """A NaN compares False with every bound: max() over the errors skipped it and the demo said ok."""
    _nan_dq(monkeypatch)
    assert not attention.demo_size("small", **attention.DEMO_SIZES["small"])
    assert "EXCEEDED" in capsys.readouterr().out


def test_attention_aborts_before_timing_a_nan_gradient(monkeypatch, capsys):
    _nan_dq(monkeypatch)
    report = attention.run(3, 1, 1, 2, 8, 8, threads=2, repeat=5)
    assert "pyvf" in report.get("aborted", ""), report.get("aborted")
    assert "time" not in report


def test_attention_aborts_before_timing_torch_given_a_wrong_mask(monkeypatch, capsys):
    """torch SDPA's errors were printed but held to no bound: with the mask transposed, its time
    and the torch / pyvf ratio were still reported."""
    torch_fns = attention.torch_fns
    monkeypatch.setattr(attention, "torch_fns", lambda q, k, v, do, mask: torch_fns(q, k, v, do, mask.T.copy()))
    report = attention.run(3, 1, 1, 2, 8, 8, threads=2, repeat=5)
    assert "torch" in report.get("aborted", ""), report.get("aborted")
    assert "time" not in report and "ratio_torch_over_pyvf" not in report


def test_each_kernel_paths_backward_is_validated_before_it_is_timed(monkeypatch):
    """path_times checked each path's forward only, then timed its forward and backward. The bug
    is planted on the paths path_times switches to (inside use_kernel_path), not on the reference
    it computes first: so the test runs on a CPU of one path too (no skip)."""
    backward, switch = pyvf.branching_attention_backward, pyvf.use_kernel_path
    inside = []

    class planted_switch(switch):  # marks the calls made under a switched path
        def __enter__(self):
            inside.append(self.path)
            return super().__enter__()

        def __exit__(self, *exc):
            inside.pop()
            return super().__exit__(*exc)

    def planted(*args, **kwargs):  # the gradients of dk and dv swapped, on the switched paths only
        dq, dk, dv = backward(*args, **kwargs)
        return (dq, dv, dk) if inside else (dq, dk, dv)
    monkeypatch.setattr(pyvf, "use_kernel_path", planted_switch)
    monkeypatch.setattr(pyvf, "branching_attention_backward", planted)
    q, k, v, do = attention.make_inputs(3, 1, 1, 2, 8, 8)
    with pytest.raises(RuntimeError, match=f"path {pyvf.kernel_paths()[0]}: differs"):
        attention.path_times(q, k, v, do, 1, 1.0, 1.0, 1.0)


# ---------------------------------------------------------------------------------------
# scaling


def test_scaling_point_with_a_nan_gradient_fails_validation():
    q, k, v, do = attention.make_inputs(3, 1, 1, 2, 8, 8)
    x64 = [x.astype(np.float64) for x in (q, k, v, do)]
    ref = (pyvf.branching_attention_reference(*x64[:3]), pyvf.branching_attention_reference_vjp(*x64))
    c = scaling.contender("pyvf", (q, k, v, do), {})
    fb = c["fb"]

    def planted():
        o, (dq, dk, dv) = fb()
        return o, (np.full_like(dq, np.nan), dk, dv)
    out = {}
    assert scaling.validate_point(out, c, ref) and out["errors"]["dq"] <= attention.BOUND32
    out = {}
    assert not scaling.validate_point(out, dict(c, fb=planted), ref)
    assert out["error"].startswith("validation failed"), out


# ---------------------------------------------------------------------------------------
# accuracy


def test_accuracy_variant_that_drops_an_output_is_not_timed(monkeypatch):
    """errors() zipped the outputs with the reference's, so a variant that returned fewer outputs
    (LayerNorm without dbeta) was checked on the ones it returned and passed."""
    backward = pyvf.nn.layers.layernorm_backward
    monkeypatch.setattr(pyvf.nn.layers, "layernorm_backward", lambda *a, **k: backward(*a, **k)[:2])
    op = accuracy.make_op("layernorm", "smoke")
    x = op.inputs(np.random.default_rng(0))
    v = accuracy.variants(op, with_torch=False)[0]
    with pytest.raises(ValueError, match="outputs"):
        accuracy.run_variant(op, x, op.reference(x), v)


# ---------------------------------------------------------------------------------------
# vq


def test_vq_contender_with_wrong_codes_is_not_timed(monkeypatch, capsys):
    """The other methods' wrong codes were only printed: one that is wrong on ordinary data (here
    the argmin over the wrong axis) was timed and its ratio to pyvf printed."""
    methods = vq.methods

    def planted():
        out = methods()
        out["torch cdist + argmin"] = lambda x, c: torch.cdist(torch.from_numpy(x), torch.from_numpy(c)).argmin(
            dim=0).numpy()[np.arange(len(x)) % len(c)]
        return out
    monkeypatch.setattr(vq, "methods", planted)
    report = vq.run(512, 64, 16, repeat=3, checked_rows=256, threads=2)
    assert any("torch cdist" in f for f in report["failures"]), report["failures"]
    assert "torch cdist + argmin" not in report["methods"]


# ---------------------------------------------------------------------------------------
# transformer and codebook: pyvf's and torch's first step compared before timing


def _transposed(grads, ndim, planted):
    """grads with the first gradient of `ndim` dimensions whose last two axes are square
    transposed in them (a weight read the wrong way round in the backward); its name in planted."""
    name = next(k for k, g in grads.items() if g.ndim == ndim and g.shape[-1] == g.shape[-2] > 1)
    planted.append(name)
    return dict(grads, **{name: np.ascontiguousarray(grads[name].swapaxes(-1, -2))})


def test_transformer_backward_bug_is_caught_before_timing(monkeypatch):
    """Only the first forward's loss was compared: a wrong gradient (here a transposed weight's)
    was timed as a training step."""
    t = transformer.worker_torch("tiny", 3)
    p = transformer.worker_pyvf("tiny", 3)
    assert common.first_step_differs(p, t) is None
    backward, planted = pyvf.Transformer.backward, []
    monkeypatch.setattr(pyvf.Transformer, "backward",
                        lambda self, *a, **k: _transposed(backward(self, *a, **k), 2, planted))
    differs = common.first_step_differs(transformer.worker_pyvf("tiny", 3), t)
    assert differs and planted[0] in differs, differs


def test_transformer_optimizer_bug_is_caught_before_timing(monkeypatch):
    """The timed step ends in AdamW's update, which nothing compared: here it goes uphill."""
    t = transformer.worker_torch("tiny", 3)
    step = pyvf.AdamW.step
    monkeypatch.setattr(pyvf.AdamW, "step", lambda self, grads: step(self, {k: -g for k, g in grads.items()}))
    differs = common.first_step_differs(transformer.worker_pyvf("tiny", 3), t)
    assert differs and "after update" in differs, differs


def test_a_nan_loss_or_checksum_is_a_difference():
    """abs(nan - t) > tol is False: a NaN loss passed the loss comparison."""
    good = dict(loss=1.5, gradients={"w": [2.0, 0.5]}, loss_after_update=1.4)
    assert common.first_step_differs(good, good) is None
    assert common.first_step_differs(dict(good, loss=float("nan")), good)
    assert common.first_step_differs(dict(good, loss_after_update=float("nan")), good)
    assert common.first_step_differs(dict(good, gradients={"w": [2.0, float("nan")]}), good)
    assert common.first_step_differs(dict(good, gradients={}), good)
    assert common.first_step_differs(dict(good, outputs={"o": [1.0, 1.0]}), good)  # on one side only


def test_checksums_tell_a_transposed_array_from_the_right_one():
    a = np.random.default_rng(0).standard_normal((8, 8))
    right, wrong = common.checksums({"w": a}), common.checksums({"w": a.T})
    assert right["w"][0] == pytest.approx(wrong["w"][0])  # the same norm
    assert abs(right["w"][1] - wrong["w"][1]) > 0.1 * right["w"][0]


def test_step_memory_is_measured_after_a_warm_up_step(monkeypatch):
    """peak_memory(step) was the first step, which brings the optimizer's moments into being (two
    arrays per parameter, in both frameworks) and any thread pool: one-time costs that peak_memory's
    contract keeps out by calling fn once first."""
    calls = []
    monkeypatch.setattr(common, "peak_memory", lambda fn: (calls.append("measured"), (fn(), 0))[1])
    fig = common.step_figures(lambda: calls.append("step") or 1.5, 3)
    assert calls[:3] == ["step", "measured", "step"] and len(calls) == 6, calls
    assert fig["loss_after_update"] == 1.5 and fig["memory"] == 0 and fig["time"] >= 0


def test_codebook_backward_and_optimizer_bugs_are_caught_before_timing(monkeypatch):
    """Only the loss of a forward (train=False) was compared: a wrong gradient (here a 3x3 conv
    weight's kernel flipped across its diagonal) was timed as a training step, and so was a wrong
    update."""
    t = codebook.worker_torch("tiny", 1)
    assert common.first_step_differs(codebook.worker_pyvf("tiny", 1), t) is None
    with monkeypatch.context() as m:
        backward, planted = pyvf.Codebook.backward, []
        m.setattr(pyvf.Codebook, "backward", lambda self, *a, **k: _transposed(backward(self, *a, **k), 4, planted))
        differs = common.first_step_differs(codebook.worker_pyvf("tiny", 1), t)
        assert differs and planted[0] in differs, differs
    step = pyvf.Adam.step  # uphill
    monkeypatch.setattr(pyvf.Adam, "step", lambda self, grads: step(self, {k: -g for k, g in grads.items()}))
    differs = common.first_step_differs(codebook.worker_pyvf("tiny", 1), t)
    assert differs and "after update" in differs, differs
