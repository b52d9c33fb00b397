"""A non-editable install (a wheel) carries the configs and runs from any folder."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    # built from a copy: setuptools writes build/ and *.egg-info into the source folder
    source = tmp_path_factory.mktemp("source")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(REPO / name, source / name)
    for name in ("src", "conf", "examples"):
        shutil.copytree(REPO / name, source / name,
                        ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", "tuned"))
    out = tmp_path_factory.mktemp("wheel")
    res = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                          "--no-build-isolation", str(source), "-w", str(out)],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    return next(out.glob("lbo-*.whl"))


def test_the_wheel_ships_every_config(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    conf = {str(p.relative_to(REPO / "conf")) for p in (REPO / "conf").rglob("*.yaml")
            if p.parent.name != "tuned"}
    assert conf and {f"lbo/conf/{c}" for c in conf} <= names
    assert "lbo/py.typed" in names
    assert "lbo/examples/stop_and_go_10hz.csv" in names  # the quickstart's log
    for run in ("comma2k19/segment.npz", "sideslip/run.npz"):  # the real runs, licensed
        folder = run.split("/")[0]
        assert {f"lbo/sim/data/{run}", f"lbo/sim/data/{folder}/LICENSE"} <= names
    assert not [n for n in names if n.endswith(".sh")]


@pytest.mark.slow
def test_an_installed_wheel_composes_its_configs_outside_the_repo(wheel, tmp_path):
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target",
                    str(site), str(wheel)], check=True, capture_output=True)
    work = tmp_path / "project"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("LBO_ROOT", "MLFLOW_TRACKING_URI")}
    env["PYTHONPATH"] = str(site)
    res = subprocess.run([sys.executable, "-c", "import lbo.core.paths as p; "
                          "print(p.CONF_DIR); print(p.REPO_ROOT); print(p.EXAMPLE_LOG)"],
                         cwd=work, env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == [str(site / "lbo" / "conf"), str(work),
                                  str(site / "lbo" / "examples" / "stop_and_go_10hz.csv")]
    assert (site / "lbo" / "examples" / "stop_and_go_10hz.csv").is_file()
    res = subprocess.run([sys.executable, "-m", "lbo.datagen", "data=smoke"], cwd=work,
                         env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
    assert list((work / "data").glob("smoke-*/train.parquet"))


def test_the_version_citation_and_changelog_agree():
    """One version: pyproject.toml's, which lbo.__version__ reads; CITATION.cff, the
    README's BibTeX and the changelog's newest entry carry it."""
    import re
    import tomllib

    import yaml

    import lbo

    version = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    assert lbo.__version__ == version
    citation = yaml.safe_load((REPO / "CITATION.cff").read_text())
    assert citation["version"] == version and citation["cff-version"] == "1.2.0"
    assert citation["references"][0]["title"] == ("Learning-based Observer Evaluated on the "
                                                  "Kinematic Bicycle Model")
    newest = re.search(r"^## \[(.+?)\]", (REPO / "CHANGELOG.md").read_text(), re.M)
    assert newest and newest.group(1) == version
    assert f"version = {{{version}}}" in (REPO / "README.md").read_text()


def test_the_lbo_console_script_runs_each_command_as_python_m_does(tmp_path):
    """``lbo <command> ...`` is ``python -m lbo.<command> ...``: the same log, byte for byte;
    ``lbo --help`` lists the commands, an unknown one is one line and exit 2."""
    script = Path(sys.executable).parent / "lbo"
    assert script.is_file()  # installed by pyproject's [project.scripts]
    res = subprocess.run([str(script), "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "usage: lbo <command>" in res.stdout
    assert all(f"  {name} " in res.stdout for name in ("train", "observe", "realdrive"))
    res = subprocess.run([str(script), "trian"], capture_output=True, text=True)
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [
        "error: unknown command 'trian'; expected one of datagen, simulate, train, tune, "
        "evaluate, observe, export, reproduce, ablation, realdrive, receiver_study (lbo --help)"]
    args = ["manoeuvre=slalom", "alpha=2", "fix_rate=10"]
    for name, cmd in (("a", [str(script), "simulate"]),
                      ("b", [sys.executable, "-m", "lbo.simulate"])):
        res = subprocess.run([*cmd, *args, f"output={tmp_path / name}.csv"], cwd=tmp_path,
                             capture_output=True, text=True)
        assert res.returncode == 0, res.stderr
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()
    bad = subprocess.run([str(script), "simulate", "alpha=-1", f"output={tmp_path / 'c.csv'}"],
                         cwd=tmp_path, capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.startswith("error: alpha")


def test_each_commands_help_lists_its_own_groups_and_explains_its_settings():
    res = subprocess.run([sys.executable, "-m", "lbo.observe", "--help"], capture_output=True,
                         text=True)
    assert res.returncode == 0, res.stderr
    out = res.stdout
    assert out.startswith("python -m lbo.observe [group=option ...] [key=value ...]")
    groups = out.split("== Groups (group=option) ==\n")[1].split("\n\n")[0].splitlines()
    assert groups == ["noise: literal, paper (default: paper)",
                      "vehicle: default (default: default)"]  # not train's model, trainer ...
    # the settings with the comments that explain them, as conf/observe.yaml holds them
    assert "plot: null              # true: <output>.png beside the output" in out
    train = subprocess.run([sys.executable, "-m", "lbo.train", "-h"], capture_output=True,
                           text=True).stdout
    assert ("model: cnn, filternet, gyro_ekf, kalmannet, lstm, slip_filter, slip_gru, "
            "split_kalmannet (default: cnn)") in train
    assert "receiver: single_antenna (default: none)" in train
    assert "  normalisation: standard  # standard: each channel's mean and std" in train
    assert "car: dynamic, gusty, kinematic (default: kinematic)" in train
    assert "sensors: drift, white (default: white)" in train


@pytest.mark.parametrize("old, new", [
    ("truth=dynamic", "car=dynamic"),
    ("truth=dynamic_drift", "car=dynamic sensors=drift"),
    ("truth.gnss_sigma=0.3", "sensors.gnss_sigma=0.3"),
    ("truth.mu=0.8", "car.mu=0.8"),
    ("+truth.speed_scale=0.02", "+sensors.speed_scale=0.02"),
    ("simulated.truth.gnss_tau=5", "simulated.sensors.gnss_tau=5"),
])
def test_the_truth_group_split_in_two_names_the_new_spelling(old, new):
    from lbo.core.cli import check_truth_split
    from lbo.core.errors import LboError

    with pytest.raises(LboError, match=f"^{re.escape(old)}: the truth group is two groups now, "
                                       rf".*; write {re.escape(new)}$"):
        check_truth_split(["data=smoke", old])
    check_truth_split(["car=dynamic", "sensors.gnss_sigma=0.3", "data.truthful=1"])


def test_an_old_truth_override_is_one_line_before_anything_runs(tmp_path):
    res = subprocess.run([sys.executable, "-m", "lbo.simulate", "truth=dynamic_drift",
                          f"output={tmp_path / 'log.csv'}", f"hydra.run.dir={tmp_path / 'run'}"],
                         capture_output=True, text=True)
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [
        "error: truth=dynamic_drift: the truth group is two groups now, the car and its "
        "sensors' errors (conf/car, conf/sensors); write car=dynamic sensors=drift"]
    assert not (tmp_path / "run").exists() and not (tmp_path / "log.csv").exists()


def test_a_config_group_set_to_null_is_one_line_not_a_traceback(tmp_path):
    res = subprocess.run([sys.executable, "-m", "lbo.train", "logger=null",
                          f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True)
    assert res.returncode == 2 and res.stderr.strip() == (
        "error: logger=null: logger is a config group; leave it out with ~logger "
        "(or pick one: logger=<option>)")
    assert not (tmp_path / "run").exists()
