"""`pyvf bench NAME` refuses a bad size, limit or output path when it parses its arguments: one
line naming the option, status 2, before anything is measured (pyvf/cli/options.py's argparse
types). In process, through pyvf.cli.main, so each case takes milliseconds."""

import pytest

from pyvf.cli import main
from pyvf.cli.bench import BENCHMARKS

BAD = [
    (["attention", "--quick", "--N", "0"], "--N", "expected a positive integer, got '0'"),
    (["attention", "--quick", "--N", "-1"], "--N", "expected a positive integer, got '-1'"),
    (["attention", "--quick", "--H", "0"], "--H", "expected a positive integer"),
    (["attention", "--quick", "--R", "0"], "--R", "expected a positive integer"),
    (["attention", "--quick", "--L", "0"], "--L", "expected a positive integer"),
    (["attention", "--quick", "--json", "nodir/a.json"], "--json", "cannot write 'nodir/a.json': the "
                                                                                   "folder 'nodir' does not exist"),
    (["attention", "--quick", "--json", "."], "--json", "'.' is a folder, not a file"),
    (["vq", "--quick", "--K", "-1"], "--K", "expected a positive integer"),
    (["vq", "--quick", "--D", "0"], "--D", "expected a positive integer"),
    (["vq", "--quick", "--M", "0"], "--M", "expected a positive integer"),
    (["scaling", "--quick", "--mem-limit-mib", "-1"], "--mem-limit-mib", "expected a positive number, got '-1'"),
    (["scaling", "--quick", "--mem-limit-mib", "nan"], "--mem-limit-mib", "expected a positive number"),
    (["scaling", "--quick", "--max-point-seconds", "-1"], "--max-point-seconds", "expected a finite number >= 0"),
    (["scaling", "--quick", "--json", "nodir/s.json"], "--json", "does not exist"),
    (["scaling", "--quick", "--views", "2,x"], "--views", "expected positive integers"),
    (["scaling", "--quick", "--sizes", "4x"], "--sizes", "expected HxDH pairs of positive integers"),
    (["accuracy", "--quick", "--repeat", "0"], "--repeat", "expected a positive integer"),
]


@pytest.mark.parametrize("argv, option, said", BAD, ids=[" ".join(b[0]) for b in BAD])
def test_a_bad_argument_is_the_parsers_one_line_error(argv, option, said, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        main(["bench", *argv])
    assert e.value.code == 2
    err = capsys.readouterr().err
    last = err.splitlines()[-1]
    assert last.startswith(f"pyvf bench {argv[0]}: error: argument {option}: ") and said in last, err
    assert "Traceback" not in err


@pytest.mark.parametrize("name", ["report", "accuracy", "hardcases", "scaling"])
def test_an_output_folder_that_is_a_file_is_refused(name, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("")
    option = "--out" if name == "report" else "--plots"
    for path, said in (("afile", "'afile' is a file, not a folder"),
                       ("afile/sub", "cannot create the folder 'afile/sub': 'afile' is a file, not a folder")):
        with pytest.raises(SystemExit) as e:
            main(["bench", name, "--quick", option, path])
        assert e.value.code == 2
        assert capsys.readouterr().err.splitlines()[-1] == f"pyvf bench {name}: error: argument {option}: {said}"


def test_good_arguments_parse(tmp_path, monkeypatch):
    """The checks refuse only what is wrong: 1 is a size, 0 turns --max-point-seconds off, a new
    folder under an existing one is an output folder."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "out").mkdir()
    parse = {name: make()[0].parse_args for name, (make, _) in BENCHMARKS.items()}
    a = parse["attention"](["--N", "1", "--H", "1", "--R", "1", "--L", "1", "--json", "out/a.json"])
    assert (a.N, a.H, a.R, a.L, a.json) == (1, 1, 1, 1, "out/a.json")
    s = parse["scaling"](["--mem-limit-mib", "0.5", "--max-point-seconds", "0", "--plots", "new/plots"])
    assert (s.mem_limit_mib, s.max_point_seconds, s.plots) == (0.5, 0.0, "new/plots")
    assert parse["report"](["--out", "out/docs"]).out == "out/docs"
    assert (parse["vq"](["--M", "1", "--K", "1", "--D", "1"]).K) == 1
