"""scripts/bench_peers.py's command line for the mapper (no benchmark is run here):
the code that maps is the checkout asked for with --repo, not the one PYTHONPATH or the
current folder point to."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench(load_script):
    return load_script("bench_peers")


def _fake_checkout(folder: Path) -> Path:
    """A folder whose gmmgp_app.cli prints where it was imported from, and its args."""
    pkg = folder / "gmmgp_app"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "cli.py").write_text("import sys\nprint(__file__)\nprint(*sys.argv[1:])\n")
    return folder


def test_the_mapper_runs_the_code_of_repo_not_of_pythonpath_or_the_current_folder(
        bench, tmp_path, monkeypatch):
    asked = _fake_checkout(tmp_path / "asked")
    other = _fake_checkout(tmp_path / "other")
    monkeypatch.chdir(other)            # started from another checkout, with it on the path
    environ = dict(os.environ, PYTHONPATH=f"{other}{os.pathsep}{tmp_path / 'extra'}")
    cmd, env, cwd = bench.mapper_command(asked, "scan.npz", "out/run0", ["--set", "a=1"],
                                         environ=environ)
    assert env["PYTHONPATH"].split(os.pathsep) == [str(asked), str(other),
                                                   str(tmp_path / "extra")]
    assert cwd == asked.resolve()
    # relative paths are the caller's, made absolute: the child starts in the repository
    assert cmd[1:] == ["-m", "gmmgp_app.cli", "run", str(other / "scan.npz"), "--out",
                       str(other / "out" / "run0"), "-q", "--set", "a=1"]
    m = bench.run_measured(cmd, env=env, cwd=cwd)   # what the benchmark runs, measured
    imported, argv = m["stdout"].splitlines()
    assert Path(imported) == asked / "gmmgp_app" / "cli.py"
    assert argv.split()[0] == "run" and m["peak_rss_mb"] > 0


def test_repo_defaults_to_the_scripts_own_checkout_and_is_named_in_the_json(
        bench, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        bench.main(["--help"])
    assert e.value.code == 0
    assert "--repo" in capsys.readouterr().out and bench.ROOT == ROOT
    with pytest.raises(SystemExit) as e:        # a folder without gmmgp_app: refused
        bench.main(["--repo", str(tmp_path), "--out", str(tmp_path / "out")])
    assert e.value.code == 2 and "holds no gmmgp_app/cli.py" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    assert bench.check_repo(ROOT) == ROOT
    with pytest.raises(ValueError, match=r"--repo .* holds no gmmgp_app/cli.py"):
        bench.check_repo(tmp_path)
    src = bench.mapper_source(ROOT)
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    assert src["repo"] == str(ROOT) and src["commit"] == head
    assert isinstance(src["modified"], bool)
    assert bench.mapper_source(tmp_path) == {"repo": str(tmp_path.resolve()), "commit": None,
                                             "modified": None}
    md = bench.markdown({"cases": {}, "mapper": src, "settings": {"repeats": 1}})
    assert f"gmmgp: the code of {ROOT} at {head}" in md
