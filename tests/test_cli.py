"""The `pyvf` command after `pip install .`: the README's commands run from a folder outside the
source tree (tmp_path) through the installed console script, each benchmark in its --quick mode,
so that what they test is the install: every module the commands need is in the package (no
imports from tests/ or tools/, no sys.path tricks), the benchmarks' worker processes find their
module, and `import pyvf` does not import torch. The other commands' checks run in this process
(pyvf.cli.main).
"""

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import pyvf
from pyvf.cli import main
from pyvf.cli.bench import NAMES, parser

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TIMEOUT = 300  # seconds per command: a hung benchmark fails instead of stalling the run


def clean_env(**extra):
    """The environment without PYTHONPATH (nothing but the installed pyvf is importable), plus extra."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env.update(extra)
    return env


def pyvf_script():
    path = shutil.which("pyvf")
    if path is None:
        pytest.fail("the `pyvf` console script is not on PATH: install the package (`pip install .`) first")
    return path


def run(args, cwd, env=None):
    """Run `pyvf *args` in cwd; return the CompletedProcess (text, stdout and stderr captured)."""
    return subprocess.run([pyvf_script(), *args], cwd=cwd, env=env or clean_env(), capture_output=True,
                          text=True, timeout=TIMEOUT)


def assert_ran(proc, *expected):
    """Exit status 0 and every expected string in stdout; on failure show the output's tail."""
    tail = f"\n--- stdout (tail) ---\n{proc.stdout[-3000:]}\n--- stderr (tail) ---\n{proc.stderr[-3000:]}"
    assert proc.returncode == 0, f"`{' '.join(proc.args[1:])}` exited with {proc.returncode}{tail}"
    for text in expected:
        assert text in proc.stdout, f"`{' '.join(proc.args[1:])}` did not print {text!r}{tail}"


def test_import_pyvf_is_the_installed_package_and_imports_no_torch_or_command_code(tmp_path):
    """`import pyvf` from outside the source tree imports the installed package, and neither torch
    nor the command line: the library's modules that do a command's work (every benchmark, the
    scenes) do not import argparse; only pyvf.cli parses arguments."""
    library = ("pyvf.bench.attention, pyvf.bench.vq, pyvf.bench.steps, pyvf.bench.scaling, "
               "pyvf.bench.accuracy, pyvf.bench.hardcases, pyvf.bench.report, "
               "pyvf.scenes.dataset, pyvf.bench.common, pyvf.verify.convert_tf, pyvf.verify.convert_torch")
    code = (f"import sys, pyvf, {library}; assert 'torch' not in sys.modules, 'pyvf imported torch'; "
            "print(sorted(m for m in sys.modules if m == 'argparse' or m.startswith('pyvf.cli') or "
            "(m.startswith('pyvf') and m.rsplit('.', 1)[-1] in ('commands', 'pipeline')))); print(pyvf.__file__)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=clean_env(), capture_output=True,
                          text=True, timeout=TIMEOUT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    commands, where = proc.stdout.strip().splitlines()
    assert commands == "[]", commands
    in_tree = os.path.realpath(where).startswith(os.path.realpath(REPO) + os.sep)
    if editable_install():  # README's development install: the sources are the installed package
        assert in_tree, f"an editable install imported another copy: {where}"
    else:
        assert not in_tree, f"imported the source tree: {where}"


def editable_install():
    """Whether pyvf was installed with `pip install -e` (PEP 610's direct_url.json says so)."""
    from importlib.metadata import distribution
    url = distribution("pyvf").read_text("direct_url.json")
    return bool(url) and json.loads(url).get("dir_info", {}).get("editable", False)


def test_python_dash_m_pyvf(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "pyvf", "--version"], cwd=tmp_path, env=clean_env(),
                          capture_output=True, text=True, timeout=TIMEOUT)
    assert_ran(proc, f"pyvf {pyvf.__version__}")


@pytest.mark.parametrize("how", ["script", "-m"])
def test_a_bad_kernel_path_is_one_line_for_the_command(how, tmp_path):
    """PYVF_ISA naming no kernel path: `pyvf` (any subcommand, --help too) and `python -m pyvf` print
    one line naming the variable and the paths there are, status 1, no traceback; the library's
    `import pyvf` still raises the ImportError (a traceback is the library's way)."""
    argv = {"script": [pyvf_script()], "-m": [sys.executable, "-m", "pyvf"]}[how]
    env = clean_env(PYVF_ISA="avx9")
    for args in (["--help"], ["demo", "--quick"]):
        proc = subprocess.run([*argv, *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=TIMEOUT)
        assert proc.returncode == 1 and proc.stdout == "", proc
        assert proc.stderr.startswith("pyvf: error: PYVF_ISA='avx9'") and proc.stderr.count("\n") == 1, proc.stderr
    lib = subprocess.run([sys.executable, "-c", "import pyvf"], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=TIMEOUT)
    assert lib.returncode == 1 and "Traceback" in lib.stderr and "ImportError: PYVF_ISA='avx9'" in lib.stderr, lib


def test_config():
    """(`pyvf config` itself: test_every_readme_command_without_torch.) The path's line names the
    features that select it and its module's vector width."""
    line = pyvf._core.config_lines()[0]
    assert f"{pyvf._core._impl.simd_bytes}-byte vectors" in line
    assert all(f in line for f in pyvf._core._NEEDS.get(pyvf.kernel_path(), ()))


def status(argv):
    """`pyvf *argv` in this process: the exit status (a parser error's SystemExit too)."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code


def test_every_readme_command_without_torch(tmp_path):
    """After `pip install .` alone (torch made unimportable): each command's quick mode runs, pyvf's
    own figures measured where torch is only a comparison column, or it stops with one line naming
    the extra it needs. Every command runs in one process (`pyvf train` covers train-codebook,
    tokenize, train-transformer and evaluate; their own options are tested in
    test_train_loops.py); the benchmarks' worker processes start from the package (scaling's slow
    points are skipped, as --max-point-seconds says);
    torch must not have been imported. (bench report runs these same benchmarks; its code is tested
    with torch in test_bench_report.py and test_bench_validation.py.)"""
    hide = tmp_path / "no-torch" / "torch"
    hide.mkdir(parents=True)
    (hide / "__init__.py").write_text("raise ModuleNotFoundError(\"No module named 'torch'\", name='torch')\n")
    env = clean_env(PYTHONPATH=str(hide.parent))
    commands = [(["config"], "kernel path:"), (["demo", "--quick", "--out", "d"], "Does pyvf beat the baselines? (context 3"),
                (["train", "--preset", "smoke", "--out", "r", "--no-progress"], "pyvf train: done"),
                (["runs", "r/codebook", "r/transformer"], "|"), (["export", "r/transformer", "-o", "now.npz"], "now.npz"),
                (["scenes", "--out", "s", "--scenes", "2", "--seed", "3", "--size", "16", "--quiet"], ""),
                (["bench", "attention", "--quick"], "dense_sdpa   skipped: torch is not installed"),
                (["bench", "vq", "--quick"], "| pyvf.vq_nearest "),
                # one worker per method at N=2, the larger N skipped as too slow (predicted)
                (["bench", "scaling", "--sizes", "1x8", "--max-point-seconds", "1e-9"], "skipped: torch is not installed"),
                (["bench", "accuracy", "--quick"], "PASS"), (["bench", "hardcases", "--quick"], "PASS")]
    script = textwrap.dedent(f"""
        import contextlib, io, sys
        from pyvf.cli import main
        for argv, expected in {commands!r}:
            out = io.StringIO()
            with contextlib.redirect_stdout(out):
                status = main(argv)
            assert status == 0 and expected in out.getvalue(), (argv, status, out.getvalue()[-2000:])
        for name in ("transformer", "codebook"):  # one line naming the extra they need
            err = io.StringIO()
            with contextlib.redirect_stderr(err):
                status = main(["bench", name, "--quick"])
            assert status == 1 and len(err.getvalue().splitlines()) == 1 and "pyvf[torch]" in err.getvalue(), err
        assert "torch" not in sys.modules, "a command imported torch"
        print("all ran")""")
    assert_ran(subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True,
                              timeout=TIMEOUT), "all ran")


# every command with --threads, with its required arguments; the benchmarks follow
THREADS_COMMANDS = [["demo"], ["evaluate", "--out", "e"], ["tokenize", "--codebook", "c", "--data", "d", "--out", "o"],
                    ["train-codebook", "--data", "d", "--out", "o", "--steps", "1"],
                    ["train-transformer", "--tokens", "t", "--out", "o", "--steps", "1"], ["train", "--out", "o"]]


@pytest.mark.parametrize("argv", THREADS_COMMANDS + [["bench", name] for name in NAMES], ids=" ".join)
def test_threads_is_one_option_checked_once(argv, capsys):
    """--threads is the same option everywhere (pyvf/cli/options.py): a positive integer of at most
    1024 (MAX_THREADS), anything else the parser's error naming it, before any work starts."""
    for bad in ("0", "x", "1025"):
        with pytest.raises(SystemExit) as e:
            main(argv + ["--threads", bad])
        assert e.value.code == 2 and "argument --threads:" in capsys.readouterr().err
    if argv[0] == "bench":
        assert parser(argv[1]).parse_args(["--threads", "3"]).threads == 3
    else:
        from pyvf.cli import build_parser
        assert build_parser().parse_args(argv + ["--threads", "3"]).threads == 3


# `pyvf bench NAME` refuses a bad option when it parses its arguments: one line naming the
# option, status 2, before anything is measured (pyvf/cli/options.py's argparse types)
BENCH_BAD = [  # (arguments, the option named)
    (["attention", "--json", "nodir/a.json"], "--json"),
    (["attention", "--json", "."], "--json"),
    (["scaling", "--max-point-seconds", "-1"], "--max-point-seconds"),
    (["scaling", "--sizes", "4x"], "--sizes"),
    (["scaling", "--sizes", "0x32"], "--sizes"),
    (["accuracy", "--plots", "afile"], "--plots"),
    (["hardcases", "--plots", "afile/sub"], "--plots"),
    (["report", "--out", "afile"], "--out"),
]


@pytest.mark.parametrize("argv, option", BENCH_BAD, ids=[" ".join(b[0]) for b in BENCH_BAD])
def test_a_bad_bench_argument_is_the_parsers_one_line_error(argv, option, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("")
    with pytest.raises(SystemExit) as e:
        main(["bench", *argv])
    assert e.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1].startswith(f"pyvf bench {argv[0]}: error: argument {option}: ")


def test_good_bench_arguments_parse(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "out").mkdir()
    parse = {name: parser(name).parse_args for name in NAMES}
    s = parse["scaling"](["--sizes", "12x64,4x32", "--max-point-seconds", "0", "--plots", "new/plots", "--json", "s.json"])
    assert (s.sizes, s.max_point_seconds, s.plots, s.json) == (((12, 64), (4, 32)), 0.0, "new/plots", "s.json")
    assert parse["report"](["--out", "out/docs", "--quick"]).out == "out/docs"


def test_bench_forwards_help(capsys):
    """`pyvf bench NAME --help` is the benchmark's own help (pyvf/cli/bench.py's parser of it)."""
    assert status(["bench", "vq", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: pyvf bench vq") and "--quick" in out, out


def torch_codebook_files(folder):
    """A small CodebookConfig as folder/config.json and its weights as folder/model.ckpt, laid out
    as the published checkpoint is (a leading "model.", a key of the loss) -> the model's state."""
    import torch
    cfg = pyvf.CodebookConfig(ch=32, ch_mult=(1, 2), num_res_blocks=1, attn_resolutions=(8,), z_channels=32,
                              embed_dim=8, n_embed=16, image_size=16)
    want = pyvf.Codebook(cfg, seed=3).state_dict()
    sd = {"model." + k: torch.tensor(v) for k, v in want.items()}  # a leading "model." is dropped
    sd["loss.discriminator.main.0.weight"] = torch.zeros(2)  # not the model's: skipped
    torch.save({"state_dict": sd, "epoch": 1}, folder / "model.ckpt")
    (folder / "config.json").write_text(json.dumps(dataclasses.asdict(cfg)))
    return want


def test_convert_torch_codebook(tmp_path, monkeypatch, capsys):
    want = torch_codebook_files(tmp_path)
    monkeypatch.chdir(tmp_path)
    assert status(["convert", "torch-codebook", "model.ckpt", "--config", "config.json", "-o", "codebook.npz"]) == 0
    assert f"wrote codebook.npz: {len(want)} arrays; skipped 1 other keys" in capsys.readouterr().out
    got = pyvf.Codebook.load(tmp_path / "codebook.npz").state_dict()
    assert set(got) == set(want)
    for name in want:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    # an output without .npz is written with it (as Model.save names files), and the line says so
    assert status(["convert", "torch-codebook", "model.ckpt", "--config", "config.json", "-o", "converted"]) == 0
    assert f"wrote converted.npz: {len(want)} arrays" in capsys.readouterr().out
    assert not (tmp_path / "converted").exists() and (tmp_path / "converted.npz").is_file()


# a mistake -> (`pyvf convert` arguments, the argument its one line on stderr names)
CONVERT_MISTAKES = {
    "config missing": (["torch-codebook", "model.ckpt", "--config", "missing.json"], "--config"),
    "config not JSON": (["torch-codebook", "model.ckpt", "--config", "model.ckpt"], "--config"),
    "checkpoint of another model": (["torch-codebook", "other.ckpt", "--config", "config.json"], "checkpoint"),
    "output folder missing": (["torch-codebook", "model.ckpt", "--config", "config.json", "-o", "nodir/x.npz"],
                              "-o/--output"),
    "tf checkpoint damaged": (["tf-transformer", "model", "--config", "tf.json"], "checkpoint"),
}


@pytest.mark.parametrize("mistake", CONVERT_MISTAKES)
def test_convert_mistakes_are_one_line(mistake, tmp_path, monkeypatch, capsys):
    """Each file a converter reads or writes is checked before the checkpoint is converted; a
    mistake is one line naming the argument, exit status 2, no traceback and nothing written.
    tensorflow is a stand-in whose reader raises an error of tensorflow's own (DataLossError)."""
    import torch
    torch_codebook_files(tmp_path)
    torch.save({"state_dict": {"other.weight": torch.zeros(2)}}, tmp_path / "other.ckpt")
    (tmp_path / "model.index").write_bytes(b"")
    fake_tensorflow(monkeypatch, tmp_path, FAKE_DAMAGED_TENSORFLOW, "tf.json")
    argv, option = CONVERT_MISTAKES[mistake]
    argv = ["convert", *argv] + ([] if "-o" in argv else ["-o", "out.npz"])
    assert status(argv) == 2
    out, err = capsys.readouterr()
    assert err.startswith(f"pyvf convert {argv[1]}: error: argument {option}: "), err
    assert err.count("\n") == 1 and out == "", err
    assert not (tmp_path / "out.npz").exists()


TF_CONFIG = pyvf.TransformerConfig(n_embeddings=64, n_head=2, d_model=32, n_layer=2, token_image_size=4,
                                   sequence_size=5, n_loss_skip=1)


def fake_tensorflow(monkeypatch, tmp_path, module, config="config.json"):
    """tmp_path/fake/tensorflow (whose __init__.py is `module`) imported as tensorflow, in this
    folder, and TF_CONFIG written to tmp_path/config."""
    (tmp_path / config).write_text(json.dumps(dataclasses.asdict(TF_CONFIG)))
    (tmp_path / "fake" / "tensorflow").mkdir(parents=True)
    (tmp_path / "fake" / "tensorflow" / "__init__.py").write_text(textwrap.dedent(module))
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path / "fake"))
    for name in [m for m in sys.modules if m == "tensorflow" or m.startswith("tensorflow.")]:
        monkeypatch.delitem(sys.modules, name)


# tensorflow's checkpoint reader meeting a damaged checkpoint: an error class of tensorflow's own
FAKE_DAMAGED_TENSORFLOW = '''
class DataLossError(Exception):
    pass


class train:
    @staticmethod
    def load_checkpoint(prefix):
        raise DataLossError(prefix + ".data-00000-of-00001 is truncated")
'''


# A stand-in for tensorflow, enough for the converter: tf.train.load_checkpoint(prefix) reads the
# checkpoint's keys and arrays from prefix + ".npz" (the real one reads model.index, model.data-*).
FAKE_TENSORFLOW = '''
import numpy as np


class _Reader:
    def __init__(self, prefix):
        with np.load(prefix + ".npz") as f:
            self.tensors = {k: f[k] for k in f.files}

    def get_variable_to_shape_map(self):
        return {k: list(v.shape) for k, v in self.tensors.items()}

    def get_tensor(self, key):
        return self.tensors[key]


class train:
    load_checkpoint = _Reader
'''


def test_convert_tf_transformer(tmp_path, monkeypatch, capsys):
    """The command end to end, with a stand-in tensorflow module (tensorflow itself is not a test
    dependency): object-based checkpoint keys, an optimizer slot and the save counter skipped."""
    want = {k: v.astype(np.float32) for k, v in pyvf.Transformer(TF_CONFIG, seed=3).state_dict().items()}
    suffix = "/.ATTRIBUTES/VARIABLE_VALUE"
    ckpt = {"model/migt/" + k + suffix: v for k, v in want.items()}
    ckpt["save_counter" + suffix] = np.array(1)
    ckpt["model/migt/ln_f/gamma/.OPTIMIZER_SLOT/optimizer/m" + suffix] = np.ones(32, np.float32)
    np.savez(tmp_path / "model.npz", **ckpt)
    fake_tensorflow(monkeypatch, tmp_path, FAKE_TENSORFLOW)
    assert status(["convert", "tf-transformer", "model", "--config", "config.json", "-o", "model_out.npz"]) == 0
    assert f"wrote model_out.npz: {len(want)} arrays; skipped 2 other keys" in capsys.readouterr().out
    got = pyvf.Transformer.load(tmp_path / "model_out.npz").state_dict()
    assert set(got) == set(want)
    for name in want:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)


def test_convert_tf_transformer_without_tensorflow(tmp_path, monkeypatch, capsys):
    """A clear message and exit status 1, not a traceback (tensorflow hidden by a module that fails
    to import, so that the test runs the same whether tensorflow is installed or not). The files
    are there: a missing one is named first (test_convert_mistakes_are_one_line)."""
    (tmp_path / "model.index").write_bytes(b"")
    fake_tensorflow(monkeypatch, tmp_path, "raise ImportError('no tensorflow here')\n")
    assert status(["convert", "tf-transformer", "model", "--config", "config.json", "-o", "out.npz"]) == 1
    assert "needs tensorflow" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["demo", "evaluate"])
def test_out_checked_before_evaluating(command, tmp_path, monkeypatch, capsys):
    """An --out that cannot be a folder is one line naming it, exit status 2, before the models are
    loaded or any scene evaluated (it used to be a traceback after the whole evaluation). Model
    files are named; they need not exist: --out is checked first."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("")
    for out in ("afile", "afile/x"):
        args = ["--quick"] if command == "demo" else ["--scenes", "1", "--context", "1"]
        assert status([command, *args, "--codebook", "cb.npz", "--transformer", "tf.npz", "--no-progress",
                       "--out", out]) == 2
        captured = capsys.readouterr()
        assert captured.err.startswith(f"pyvf {command}: error: argument --out: "), captured.err
        assert captured.err.count("\n") == 1 and "evaluating" not in captured.out, captured.err


def test_import_from_the_checkout_root_names_the_cause():
    """`python` started in the repository root finds the source tree's pyvf/ first, which has no
    kernels: the error says so and how to fix it (not only that the extension is missing). With the
    editable install the README gives for development, the same import works and is the source."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    assert os.path.isdir(os.path.join(root, "csrc")) and os.path.isdir(os.path.join(root, "pyvf"))
    proc = subprocess.run([sys.executable, "-c", "import pyvf; print(pyvf.__file__)"], cwd=root,
                          capture_output=True, text=True)
    if os.path.realpath(pyvf.__file__).startswith(os.path.realpath(root) + os.sep):  # editable install
        assert proc.returncode == 0 and proc.stdout.strip() == os.path.join(root, "pyvf", "__init__.py"), proc
        return
    assert proc.returncode != 0
    assert "imported pyvf from the source tree" in proc.stderr and "another folder" in proc.stderr \
        and "pip install --no-build-isolation -e ." in proc.stderr, proc.stderr


def test_one_thread_setting_for_the_kernels_and_blas():
    """pyvf.threads sets the kernels and numpy's BLAS pool together and the block puts both back
    (its refusals, and PYVF_NUM_THREADS's: test_threads.py)."""
    from threadpoolctl import threadpool_info

    def blas():
        return sorted({p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"})

    before_k, before_b = pyvf.num_threads(), blas()
    assert before_b, "numpy has a BLAS pool"
    with pyvf.threads(1):
        assert pyvf.num_threads() == 1 and blas() == [1]
    assert pyvf.num_threads() == before_k and blas() == before_b
