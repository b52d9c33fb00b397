"""The onavdata hill drive as lbo logs (issue 36): the importer on a slice of it, the lever
arm and latency fit, the one-line refusals, and ``python -m lbo.realdrive`` end to end.
Needs the optional extra ``lbo[real]`` (installed by ``make install``)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from helpers import cli, observe, train_in_own_store
from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.filters.gyro_noise import GyroNoise
from lbo.logs import hguide
from lbo.logs.io import check_log
from lbo.serve.observer import Observer
from lbo.sim.vehicle import Vehicle

CONF = Path(__file__).resolve().parents[1] / "conf"

pytest.importorskip("onavdata", reason="the optional extra lbo[real] is not installed")


@pytest.fixture(scope="module")
def drive() -> pd.DataFrame:
    return hguide.read()


def test_only_the_hill_drive_is_read():
    line = (r"^drive 'another drive': lbo reads only the onavdata hill drive "
            r"\('2021-04-27 HGuide n380 Car Hill Driving'\)$")
    with pytest.raises(LboError, match=line):
        hguide.read("another drive")


def _hill_folder() -> Path:
    import onavdata

    return Path(onavdata.__file__).parent / "data" / "HGuide n380" / hguide.HILL_FOLDER


def test_a_recording_folder_reads_as_the_drive_does(drive):
    pd.testing.assert_frame_equal(hguide.read_folder(_hill_folder()), drive)


def test_a_users_recording_is_cut_to_the_span_every_stream_covers(tmp_path):
    """The first 261 s of the hill drive written as a user's recording (plain CSV files),
    its velocity stream ending 2 s before the others, as on another n380 recording: the log
    ends where the velocity does, its every speed given, and reads as a log."""
    recording = tmp_path / "rec"
    recording.mkdir()
    starts = {}
    for stream in hguide.STREAMS:
        df = pd.read_csv(_hill_folder() / f"n380-{stream}.csv.zip", skipinitialspace=True)
        starts[stream] = df
    t0 = starts["position"].loc[starts["position"]["SystemTov"] > 0, "SystemTov"].min()
    for stream, df in starts.items():
        end = t0 + (259.0 if stream == "velocity" else 261.0)
        df[df["SystemTov"] < end].to_csv(recording / f"n380-{stream}.csv", index=False)
    log = hguide.to_log(hguide.read_folder(recording))
    assert np.isfinite(log[["V", "delta", "r_m", "x", "y", "psi"]].to_numpy()).all()
    full = hguide.read_folder(recording)
    ins = full[full[hguide._INS["lat"]].notna()]
    assert ins[hguide._INS["vn"]].isna().sum() > 150  # the velocity's last 2 s are missing
    last_velocity = ins.index[ins[hguide._INS["vn"]].notna()][-1]
    assert log["t"].iloc[-1] == pytest.approx(last_velocity - ins.index[0], abs=0.02)
    check_log(log)


def test_a_recording_folder_that_is_not_one_is_one_line(tmp_path):
    with pytest.raises(LboError, match=r"^recording: .*missing is not a folder \(give the "):
        hguide.read_folder(tmp_path / "missing")
    (tmp_path / "n380-position.csv").write_text("SystemTov\n1.0\n")
    with pytest.raises(LboError, match=r"^recording: .* has no n380-velocity\.csv \(or "
                                       r"\.csv\.zip\); an n380 recording holds "):
        hguide.read_folder(tmp_path)
    other = _hill_folder().parents[1] / "GNSS Applications and Methods"  # not the hill drive
    with pytest.raises(LboError, match=r"^recording: .* is an onavdata drive other than the "
                                       r"hill drive; lbo reads only the hill drive"):
        hguide.read_folder(other)


def test_the_lever_arm_and_latency_bring_the_fixes_onto_the_truth(drive):
    al = hguide.fit_alignment(drive)
    # the INS case is turned about 2 degrees against the car: its velocity, driving
    # straight, points that far off its heading
    assert 0.02 < al.boresight < 0.05
    # the antenna sits about 1.3 m behind the INS, on the car's axis; fixes are logged
    # within a few tens of ms of their instant
    assert -2.0 < al.lever[0] < -0.5 and abs(al.lever[1]) < 0.3
    assert abs(al.latency) <= 0.1
    assert al.rms_after < 0.5 * al.rms_before and al.fixes > 100


def test_a_slice_becomes_a_log_that_lbo_reads(drive):
    """The first drive (100 s to 230 s in): fixes at 1 Hz without a heading, accuracies and
    velocities at the fix rows, inputs and truth at 50 Hz; the log passes lbo's checks."""
    t = drive.index.to_numpy()
    part = drive[(t >= t[0] + 100) & (t < t[0] + 230)]
    vehicle = Vehicle()
    log = hguide.to_log(part, vehicle, hguide.fit_alignment(drive))
    assert np.allclose(np.diff(log["t"]), vehicle.dt)
    fix = log["x_m"].notna()
    assert 125 <= fix.sum() <= 131 and log["psi_m"].isna().all()
    for c in ("sx_m", "sy_m", "ve_m", "vn_m", "sv_m"):
        assert (log[c].notna() == fix).all()
    assert (log.loc[fix, ["sx_m", "sy_m"]] > 0).all().all()
    assert check_log(log, "slice") is True
    # the speed input agrees with the receiver's own speed at the fixes, the heading with
    # its course where the car moves
    speed = np.hypot(log.loc[fix, "ve_m"], log.loc[fix, "vn_m"])
    assert np.median(np.abs(speed - log.loc[fix, "V"].abs())) < 0.1
    moving = fix & (log["V"] > 5)
    course = np.arctan2(log.loc[moving, "vn_m"], log.loc[moving, "ve_m"])
    off = wrap_angle(course - log.loc[moving, "psi"])
    # the truth's heading is the car's (the boresight turns the INS's by 35 mrad): the
    # receiver's course is centred on it (27 mrad off without the boresight)
    assert np.median(np.abs(off)) < 0.03 and abs(np.median(off)) < 0.015
    # the gyro's yaw rate is the truth's heading rate
    rate = np.gradient(np.unwrap(log["psi"]), vehicle.dt)
    assert np.corrcoef(rate, log["r_m"])[0, 1] > 0.95


def test_the_spans_cut_in_the_stops_and_keep_one_drive_each(drive):
    log = hguide.to_log(drive)
    parts = hguide.spans(log)
    assert sum(len(p) for p in parts.values()) == len(log)
    for name, part in parts.items():
        assert part["t"].iloc[0] == 0.0
        assert part["V"].abs().iloc[[0, -1]].max() < 0.5, name  # cut where the car stands
        assert (part["V"].abs() > 5).any(), name


@pytest.fixture(scope="module")
def hill_log(drive) -> pd.DataFrame:
    return hguide.to_log(drive)


def test_the_drives_are_cut_in_the_long_stops(hill_log):
    parts = hguide.drives(hill_log)
    assert len(parts) == 3 and sum(len(p) for p in parts) == len(hill_log)
    for part in parts:
        assert part["t"].iloc[0] == 0.0
        assert part["V"].abs().iloc[[0, -1]].max() < hguide.STILL_SPEED  # cut where it stands
        assert (part["V"].abs() > 5).any()
    # the same rows, in order: the second drive begins where the first ends
    assert np.array_equal(parts[1][["x", "y"]].to_numpy(),
                          hill_log[["x", "y"]].to_numpy()[len(parts[0]):len(parts[0])
                                                          + len(parts[1])])
    # a stop shorter than STOP_S is part of the drive; a log that never moves has none
    assert len(hguide.drives(hill_log, stop_s=1e4)) == 1
    with pytest.raises(LboError, match="^the log never moves faster than 0.5 m/s: it holds no "
                                       "drive$"):
        hguide.drives(hill_log.assign(V=0.0))


@pytest.fixture(scope="module")
def short_drives(hill_log) -> list[pd.DataFrame]:
    """The hill drive's three drives, each cut to 20 s from its first course over ground, and
    5 s before it (lean: the whole drives take minutes to learn on and score)."""
    from lbo.scoring.receiver import scored_rows

    short = []
    for part in hguide.drives(hill_log):
        first = int(np.argmax(scored_rows(part)))
        short.append(part.iloc[max(first - 250, 0):first + 1000].reset_index(drop=True))
    return short


@pytest.mark.slow
def test_leave_one_drive_out_never_shows_a_fold_its_drive(short_drives):
    """A planted mark on each drive: the learner of fold k never gets drive k, gets every
    other, and each drive is scored once, by its own fold (on 20 s of each drive: which
    drive goes where does not hang on their length)."""
    from omegaconf import OmegaConf

    from lbo.scoring import drives as across
    from lbo.scoring.receiver import EKF
    from lbo.sim.noise import Noise

    parts = [p.assign(mark=k) for k, p in enumerate(short_drives)]
    seen: dict[int, list[int]] = {}

    def learn(k, train):
        seen[k] = sorted(int(p["mark"].iloc[0]) for p in train)
        return across.Fold({}, {})

    table = across.leave_one_out(parts, learn, ["ekf"], Vehicle(),
                                 Noise.from_cfg(OmegaConf.load(CONF / "noise" / "paper.yaml")),
                                 progress=None)
    assert seen == {0: [1, 2], 1: [0, 2], 2: [0, 1]}
    assert table.groupby("drive").size().to_dict() == {1: 4, 2: 4, 3: 4}
    assert (table.loc[table["estimator"] == EKF, "vs_ekf"] == 1.0).all()
    wide = across.summary(table)
    ratios = wide[["drive 1", "drive 2", "drive 3"]].to_numpy()
    assert np.allclose(wide["mean"], ratios.mean(1)) and np.allclose(wide["worst"],
                                                                     ratios.max(1))
    assert list(wide["estimator"]) == list(table["estimator"].iloc[:4])
    assert f"| {EKF} | 1.000 | 1.000 | 1.000 | 1.000 | 1.000 |" in across.markdown(wide)
    with pytest.raises(LboError, match="^leave-one-drive-out needs two drives or more, got 1$"):
        across.folds(1)


@pytest.mark.slow
def test_realdrive_learns_on_the_other_drives_and_scores_each(short_drives, tmp_path, capsys):
    """lbo.realdrive's leave-one-drive-out (across_drives=true, its default), on 20 s of each
    drive from its first course over ground, and 5 s before it (lean: the whole drives take
    minutes): a noise learned per fold, written, and the table of each drive."""
    from omegaconf import OmegaConf

    from lbo.learn.gyro_fit import Settings
    from lbo.realdrive import ACROSS, _across_drives
    from lbo.sim.noise import Noise

    # 5 s segments: the filter steps through half as many rows a pass (the default is 10 s)
    learn = Settings(epochs=1, segment_s=5.0, lr=0.1, objective="innovations")
    wide = _across_drives(learn, ["ekf"], short_drives, Vehicle(),
                          Noise.from_cfg(OmegaConf.load(CONF / "noise" / "paper.yaml")),
                          tmp_path)
    drives = pd.read_csv(tmp_path / "drives.csv")
    assert sorted(set(drives["drive"])) == [1, 2, 3]
    across = drives[drives["estimator"] == ACROSS]
    assert len(across) == 3 and np.isfinite(across["vs_ekf"]).all()
    noises = [GyroNoise.load(tmp_path / f"gyro_noise_without_drive{k}.json") for k in (1, 2, 3)]
    assert len(set(noises)) == 3  # each fold its own
    assert f"| {ACROSS} |" in (tmp_path / "drives.md").read_text()
    assert list(wide.columns) == ["estimator", "drive 1", "drive 2", "drive 3", "mean", "worst"]
    out = capsys.readouterr().out
    assert "leave-one-drive-out over 3 drives: the gyro EKF's noise learned on the others " \
           "(1 epochs, innovations' likelihood, no truth read; the epoch kept by the same " \
           "drives), scored on each" in out
    assert "drive 2 of 3, learned on drives 1, 3: best " in out


@pytest.mark.parametrize(("keep", "expected"), [
    ("same", [([1, 2], [1, 2]), ([0, 2], [0, 2]), ([0, 1], [0, 1])]),
    ("held_out", [([1], [2]), ([0], [2]), ([0], [1])])])
def test_each_folds_noise_is_kept_by_the_drives_across_keep_names(short_drives, tmp_path,
                                                                   monkeypatch, capsys, keep,
                                                                   expected):
    """across_keep: a planted mark on each drive says which drives each fold's noise fit
    learned on and which kept its epoch (the fit itself stood in for: its start is scored)."""
    from types import SimpleNamespace

    from omegaconf import OmegaConf

    from lbo.learn import gyro_fit
    from lbo.learn.gyro_fit import Settings
    from lbo.realdrive import ACROSS, KEEPS, _across_drives
    from lbo.sim.noise import Noise

    seen = []

    def fit(train_logs, val_logs, vehicle, R, start, **kw):
        seen.append(([int(p["mark"].iloc[0]) for p in train_logs],
                     [int(p["mark"].iloc[0]) for p in val_logs]))
        return SimpleNamespace(noise=start)

    monkeypatch.setattr(gyro_fit, "fit", fit)
    drives = [p.assign(mark=k) for k, p in enumerate(short_drives)]
    wide = _across_drives(Settings(epochs=1, segment_s=5.0, lr=0.1), ["ekf"], drives, Vehicle(),
                          Noise.from_cfg(OmegaConf.load(CONF / "noise" / "paper.yaml")),
                          tmp_path, held_out=keep == "held_out")
    assert keep in KEEPS and seen == expected
    assert np.isfinite(wide.set_index("estimator").loc[ACROSS, "mean"])
    kept = "by the last of them" if keep == "held_out" else "by the same drives"
    assert f"(1 epochs, truth; the epoch kept {kept}), scored on each" in capsys.readouterr().out


@pytest.fixture(scope="module")
def narrow_cnn(smoke_data, tmp_path_factory) -> str:
    """A receiver CNN-N60 trained on the smoke sets, narrow (4 channels, 16 units; the paper's
    are 16, 16, 64): realdrive runs it over every window of the drives, and its width is no
    part of what is checked. Its checkpoint, which the tests read and none changes."""
    _, out, _ = train_in_own_store(tmp_path_factory.mktemp("narrow_cnn"), smoke_data,
                                   "experiment=receiver", "data=smoke", "trainer.max_epochs=1",
                                   "trainer.limit_train_batches=2", "window=60", "batch_size=64",
                                   "~callbacks.evaluation", "model.conv_channels=4",
                                   "model.feature_channels=4", "model.dense_units=16")
    return out["checkpoint"]


@pytest.mark.slow
def test_leave_one_drive_out_scores_each_net_as_trained_and_fine_tuned_on_the_others(
        short_drives, narrow_cnn, tmp_path, monkeypatch, capsys):
    """With nets (and no noise to learn): each net scored on every drive as it was trained,
    on simulated receivers alone, and fine-tuned per fold on the drives other than the one
    scored, trained on the first of them and kept by the second (a planted mark on each drive
    says which fold saw which)."""
    from omegaconf import OmegaConf

    from lbo.learn import net_fit
    from lbo.learn.gyro_fit import Settings
    from lbo.realdrive import ACROSS, FIT_OTHER_DRIVES, _across_drives
    from lbo.sim.noise import Noise

    seen: dict[str, tuple[list[int], list[int]]] = {}
    real_fit = net_fit.fit_and_write

    def fit_and_write(path, source, train_logs, val_logs, where, **kw):
        seen[path.name] = ([int(p["mark"].iloc[0]) for p in train_logs],
                           [int(p["mark"].iloc[0]) for p in val_logs])
        return real_fit(path, source, train_logs, val_logs, where, **kw)

    monkeypatch.setattr(net_fit, "fit_and_write", fit_and_write)
    drives = [p.assign(mark=k) for k, p in enumerate(short_drives)]
    fit = {"epochs": 1, "lr": 3e-4, "batch": 64, "seed": 0}
    wide = _across_drives(Settings(epochs=0, segment_s=5.0, lr=0.1), ["ekf"], drives, Vehicle(),
                          Noise.from_cfg(OmegaConf.load(CONF / "noise" / "paper.yaml")),
                          tmp_path, nets=[net := Observer.load(narrow_cnn)],
                          trainable={narrow_cnn: net}, fit=fit)
    assert seen == {"cnn-N60_without_drive1.ckpt": ([1], [2]),
                    "cnn-N60_without_drive2.ckpt": ([0], [2]),
                    "cnn-N60_without_drive3.ckpt": ([0], [1])}
    rows = wide.set_index("estimator")
    for label in ("cnn-N60 (window), receiver's accuracy and velocity",
                  f"cnn-N60, {FIT_OTHER_DRIVES}"):
        assert np.isfinite(rows.loc[label, ["drive 1", "drive 2", "drive 3"]].to_numpy(float)).all()
    assert ACROSS not in rows.index  # no noise learned with 0 epochs
    for k in (1, 2, 3):
        obs = Observer.load(tmp_path / f"cnn-N60_without_drive{k}.ckpt")
        assert obs.meta["trained_on"].startswith(f"on the hill drive's drives but drive {k}")
    assert ("leave-one-drive-out over 3 drives: 1 learned observer(s) as trained, and 1 "
            "fine-tuned on the others (1 epochs), scored on each") in capsys.readouterr().out


@pytest.mark.slow
def test_realdrive_writes_the_spans_and_scores_every_classical_observer(tmp_path):
    # an epoch of each noise fit, on two simulated drives, keeps it lean (make real-drive
    # runs 12 epochs each, on four)
    res = cli("lbo.realdrive", f"output_dir={tmp_path}", "learn.epochs=1", "learn.simulated=1",
              "simulated.drives=2", "across_drives=false", "outages.length_s=10", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    table = pd.read_csv(tmp_path / "results.csv")
    # the same observers through 10 s outages every 25 s while moving (lbo.scoring.outages)
    through = pd.read_csv(tmp_path / "outages.csv").set_index("estimator")
    assert list(through.index) == list(table["estimator"].iloc[1:])  # every observer's row
    assert (through["outages"] == 2).all() and (through["end_m"] > 0).all()  # docs/logs.md 11
    assert through.loc["ekf, receiver's accuracy and velocity", "end_vs_ekf"] == 1.0
    # dead reckoning on the gyro holds the heading through an outage; the course does not
    assert through.loc["gyro, receiver's accuracy and velocity", "end_m"] < \
        through.loc["ekf, receiver's accuracy and velocity", "end_m"]
    assert (tmp_path / "outages.png").stat().st_size > 10_000
    assert "GNSS outages of 10 s (every 25 s while moving)" in res.stdout
    assert len(table) == 10 and np.isfinite(table[["x_m", "y_m", "psi_mrad"]]).all().all()
    assert table.set_index("estimator").loc["ekf, receiver's accuracy and velocity",
                                            "vs_ekf"] == 1.0
    rows = table.set_index("estimator")[["x_m", "y_m", "psi_mrad"]]
    raw = rows.iloc[0]
    ekf = rows.loc["ekf, receiver's accuracy and velocity"]
    blind = rows.loc["ekf, lbo's R, no velocity"]
    gyro = rows.loc["gyro, receiver's accuracy and velocity"]
    learned = rows.loc["gyro, noise learned on the train span"]
    # the receiver's channels are what bring the EKF to the raw fixes' level; the gyro EKF
    # goes below them on every variable (docs/logs.md)
    assert ekf["x_m"] < 0.8 * blind["x_m"] and ekf["psi_mrad"] < 0.8 * blind["psi_mrad"]
    assert ekf["x_m"] < 1.2 * raw["x_m"] and ekf["y_m"] < 1.2 * raw["y_m"]
    assert (gyro < raw).all() and (gyro < ekf).all()
    # one epoch already moves the noise the way the validation span gains (docs/logs.md)
    history = pd.read_csv(tmp_path / "gyro_noise_history.csv")
    assert len(history) == 2 and history["val"].iloc[-1] < 1.0
    assert (learned < raw).all()
    for name in ("gyro_noise_simulated", "gyro_noise_finetuned"):
        GyroNoise.load(tmp_path / f"{name}.json")
        assert len(pd.read_csv(tmp_path / f"{name}_history.csv")) == 2
    assert "on 2 simulated drives (stop_and_go, receiver single_antenna)" in res.stdout
    assert not (tmp_path / "drives.md").exists()  # across_drives=false
    for k in ("train", "val", "test"):
        assert (tmp_path / f"hill_{k}.parquet").is_file()
    assert (tmp_path / "test.png").stat().st_size > 10_000
    assert "lever arm" in res.stdout and "| ekf, receiver's accuracy and velocity |" in res.stdout
    # a span log goes through lbo.observe as it is
    obs = observe("observer=ukf", f"input={tmp_path / 'hill_val.parquet'}",
                  f"output={tmp_path / 'val_est.csv'}", cwd=tmp_path)
    assert obs.returncode == 0, obs.stderr
    learned_run = observe("observer=gyro", f"gyro_noise={tmp_path / 'gyro_noise.json'}",
                          f"input={tmp_path / 'hill_test.parquet'}",
                          f"output={tmp_path / 'test_est.csv'}", cwd=tmp_path)
    assert learned_run.returncode == 0, learned_run.stderr
    assert ("receiver: sx_m, sy_m, ve_m, vn_m, sv_m taken (reported accuracy as R, velocity "
            "as course over ground); r_m not read by ukf (observer=gyro reads it, and a "
            "net trained with experiment=receiver, the window filter with model.gyro=true)") \
        in obs.stdout


@pytest.mark.slow
def test_realdrive_trains_a_receiver_net_on_the_train_span(narrow_cnn, tmp_path):
    # realdrive runs the net over every window of the spans three times over (fine-tuned,
    # from scratch, scored)
    res = cli("lbo.realdrive", f"output_dir={tmp_path / 'rd'}", "observers=[ekf]",
              "learn.epochs=0", "learn.simulated=0", f"nets=[{narrow_cnn}]",
              "net_fit.epochs=1", "across_drives=false", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    rows = pd.read_csv(tmp_path / "rd" / "results.csv").set_index("estimator")
    for label in ("cnn-N60 (window), receiver's accuracy and velocity",
                  "cnn-N60, fine-tuned on the train span",
                  "cnn-N60, trained on the train span only"):
        assert np.isfinite(rows.loc[label, ["x_m", "y_m", "psi_mrad"]].to_numpy(float)).all()
    # the CNN gives none where its window holds no heading: measured on the EKF's same rows
    assert rows.loc["cnn-N60 (window), receiver's accuracy and velocity", "rows"] < \
        rows.loc["ekf, receiver's accuracy and velocity", "rows"]
    for ratio in ("vs_ekf_same_rows", "vs_ekf_moving"):
        assert np.isfinite(rows[ratio].iloc[1:]).all()
        assert np.isnan(rows[ratio].iloc[0])  # the raw fixes
    assert rows.loc["ekf, receiver's accuracy and velocity", "vs_ekf_moving"] == 1.0
    for kind in ("finetuned", "span"):
        history = pd.read_csv(tmp_path / "rd" / f"cnn-N60_{kind}_history.csv")
        assert list(history["epoch"]) == [0, 1]
        obs = Observer.load(tmp_path / "rd" / f"cnn-N60_{kind}.ckpt")
        assert obs.meta["trained_on"].startswith("on the hill drive's train span, ")
    assert "training cnn-N60 on the hill drive's train span, from scratch" in res.stdout


def test_without_the_extra_and_with_a_bad_observer_it_is_one_line(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "onavdata", None)  # import onavdata -> ImportError
    with pytest.raises(LboError, match=r"^the onavdata package is not installed: "
                                       r"pip install 'lbo\[real\]'$"):
        hguide.read()
    monkeypatch.delitem(sys.modules, "onavdata")
    res = cli("lbo.realdrive", f"output_dir={tmp_path}", "observers=[ekf,pcrb]", cwd=tmp_path)
    assert res.returncode == 2 and res.stderr.startswith("error: observers: pcrb is a bound")
    res = cli("lbo.realdrive", f"output_dir={tmp_path}", "learn.epochs=-1", cwd=tmp_path)
    assert res.returncode == 2 and res.stderr.strip() == (
        "error: learn.epochs must be an integer >= 0, got -1")
    res = cli("lbo.realdrive", f"output_dir={tmp_path}", "net_fit.lr=0", cwd=tmp_path)
    assert res.returncode == 2 and res.stderr.startswith("error: net_fit.lr must be")
    res = cli("lbo.realdrive", f"output_dir={tmp_path}", "across_drives=yes", cwd=tmp_path)
    assert res.stderr.strip().splitlines()[-1] == (
        "error: across_drives must be true or false, got 'yes'")
    res = cli("lbo.realdrive", f"output_dir={tmp_path}", "across_keep=last", cwd=tmp_path)
    assert res.returncode == 2 and res.stderr.strip().splitlines()[-1] == (
        "error: across_keep must be one of ['same', 'held_out'], got 'last'")
    res = cli("lbo.realdrive", f"output_dir={tmp_path}", "learn.ahead_s=3", cwd=tmp_path)
    assert res.stderr.strip().splitlines()[-1] == (
        "error: learn.ahead_s applies to learn.objective=innovations (the fit by the fixes' "
        "likelihood), got learn.objective=truth")
    res = cli("lbo.realdrive", f"output_dir={tmp_path}", "learn.objective=nll", cwd=tmp_path)
    assert res.returncode == 2 and res.stderr.strip() == (
        "error: learn.objective must be one of ['truth', 'innovations'], got 'nll'")
    assert not any(tmp_path.iterdir())
