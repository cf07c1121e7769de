"""`pyvf bench NAME` refuses a bad option when it parses its arguments: one line naming the option,
status 2, before anything is measured (pyvf/cli/options.py's argparse types). In process."""

import pytest

from pyvf.cli import main
from pyvf.cli.bench import BENCHMARKS

BAD = [  # (arguments, the option named)
    (["attention", "--json", "nodir/a.json"], "--json"),
    (["attention", "--json", "."], "--json"),
    (["scaling", "--max-point-seconds", "-1"], "--max-point-seconds"),
    (["scaling", "--sizes", "4x"], "--sizes"),
    (["scaling", "--sizes", "0x32"], "--sizes"),
    (["accuracy", "--plots", "afile"], "--plots"),
    (["hardcases", "--plots", "afile/sub"], "--plots"),
    (["report", "--out", "afile"], "--out"),
]


@pytest.mark.parametrize("argv, option", BAD, ids=[" ".join(b[0]) for b in BAD])
def test_a_bad_argument_is_the_parsers_one_line_error(argv, option, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("")
    with pytest.raises(SystemExit) as e:
        main(["bench", *argv])
    assert e.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1].startswith(f"pyvf bench {argv[0]}: error: argument {option}: ")


def test_good_arguments_parse(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "out").mkdir()
    parse = {name: make().parse_args for name, (make, _) in BENCHMARKS.items()}
    s = parse["scaling"](["--sizes", "12x64,4x32", "--max-point-seconds", "0", "--plots", "new/plots", "--json", "s.json"])
    assert (s.sizes, s.max_point_seconds, s.plots, s.json) == (((12, 64), (4, 32)), 0.0, "new/plots", "s.json")
    assert parse["report"](["--out", "out/docs", "--quick"]).out == "out/docs"
