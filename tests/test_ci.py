""".ci/run fails when a step fails: run on a copy with stand-ins for pip, pyvf and pytest on PATH."""

import os
import shutil
import stat
import subprocess

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CI = os.path.join(ROOT, ".ci", "run")


def _stub(folder, name, status):
    path = os.path.join(folder, name)
    with open(path, "w") as f:
        f.write(f"#!/bin/sh\necho {name} \"$@\" >> \"$STUB_LOG\"\nexit {status}\n")
    os.chmod(path, os.stat(path).st_mode | stat.S_IEXEC)


@pytest.mark.parametrize("broken, ran", [
    ("pip", ["pip install ."]),  # a failed build stops the run: no demo, no tests on an older install
    ("pyvf", ["pip install .", "pyvf demo"]),
    ("pytest", ["pip install .", "pyvf demo", "pip install -r tests/requirements.txt", "pytest"]),
])
def test_a_failed_step_fails_the_ci_script(tmp_path, broken, ran):
    assert os.path.exists(CI) and shutil.which("bash"), "the tests run from the source tree, with bash"
    repo = tmp_path / "repo"
    (repo / ".ci").mkdir(parents=True)
    shutil.copy(CI, repo / ".ci" / "run")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name in ("pip", "pyvf", "pytest"):
        _stub(str(bin_dir), name, 1 if name == broken else 0)
    log = tmp_path / "calls"
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}", STUB_LOG=str(log))
    proc = subprocess.run(["bash", str(repo / ".ci" / "run")], env=env, capture_output=True, text=True,
                          stdin=subprocess.DEVNULL, timeout=60)
    assert proc.returncode != 0, proc.stdout + proc.stderr
    assert "failed" in proc.stderr
    assert log.read_text().split("\n")[:-1] == ran
