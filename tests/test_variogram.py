"""The receiver's variogram (lbo.learn.variogram): on fixes and courses whose slow and white
errors are known it reads their size and correlation, it reads no truth, a gap is no lag, and
the gyro EKF's fit with ``receiver_noise="variogram"`` keeps the factors it gives and learns
the rest (issue 70)."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from helpers.commands import observe, one_line_error
from lbo.core.errors import LboError
from lbo.filters.gyro_noise import GyroNoise
from lbo.learn import gyro_fit
from lbo.learn.gyro_fit import Settings
from lbo.learn.variogram import (
    COURSE_SILL_S,
    SILL_S,
    course_errors,
    fix_errors,
    offsets,
    receiver_scales,
)
from lbo.sim import gyro_drive
from lbo.sim.truth import gauss_markov

WHITE, DRIFT, TAU = 0.1, 0.4, 4.0  # m, m, s: slow errors four times the white ones
COURSE_WHITE, COURSE_DRIFT = 0.002, 0.01  # rad, the course's, with the same time


def drive(seed: int, fixes: int = 2000, sv: float = 0.02, course: bool = False
          ) -> pd.DataFrame:
    """A receiver's log at 1 Hz (fixes at every row): the antenna on a circle of 200 m at
    10 m/s, its fixes off by white noise and a Gauss-Markov drift of known sizes, its speed
    off by ``sv`` m/s white, the accuracy reported as 0.5 m; the gyro's exact turn; the truth
    in x, y, psi. With ``course``, the velocity's direction is off by the course's errors too
    (integrated, they would move the fixes' variogram by metres)."""
    rng = np.random.default_rng(seed)
    t = np.arange(fixes, dtype=float)
    angle = t * 10.0 / 200.0
    x, y = 200.0 * np.cos(angle), 200.0 * np.sin(angle)
    error = (WHITE * rng.standard_normal((fixes, 2))
             + gauss_markov((1, fixes, 2), 1.0, TAU, DRIFT, rng)[0])
    off = (COURSE_WHITE * rng.standard_normal(fixes)
           + gauss_markov((1, fixes), 1.0, TAU, COURSE_DRIFT, rng)[0]) * course
    speed = 10.0 + sv * rng.standard_normal(fixes)
    v = speed[:, None] * np.stack([-np.sin(angle + off), np.cos(angle + off)], 1)
    return pd.DataFrame({"t": t, "x_m": x + error[:, 0], "y_m": y + error[:, 1],
                         "sx_m": 0.5, "sy_m": 0.5, "ve_m": v[:, 0], "vn_m": v[:, 1], "sv_m": sv,
                         "V": 10.0, "r_m": 0.05, "x": x, "y": y, "psi": angle + np.pi / 2})


def expected(lag: float, white: float = WHITE, drift: float = DRIFT) -> float:
    """Half the mean square change of the error over ``lag`` s, per axis."""
    return white**2 + drift**2 * (1.0 - np.exp(-lag / TAU))


def test_it_reads_the_size_and_the_correlation_of_errors_it_was_not_told():
    logs = [drive(seed) for seed in range(3)]
    got = fix_errors(logs)
    assert got.step == pytest.approx(expected(1.0), rel=0.1)
    assert got.sill == pytest.approx(np.mean([expected(s) for s in SILL_S]), rel=0.1)
    assert got.reported == pytest.approx(0.25)
    assert got.pairs == 3 * 1999
    # the errors' correlation from one fix to the next, and the variance a white-noise
    # filter should give each fix: far above both the errors' and the reported variance
    sill = WHITE**2 + DRIFT**2
    assert got.rho == pytest.approx(1.0 - expected(1.0) / sill, abs=0.03)
    assert got.long_run == pytest.approx(got.sill * (1 + got.rho) / (1 - got.rho))
    assert got.long_run > 5 * sill
    assert got.accuracy_scale == pytest.approx(np.sqrt(got.long_run / 0.25))
    # white errors alone: no correlation, and the factor is the true sigma over the reported
    white = fix_errors([drive(seed).assign(x_m=lambda d, s=seed: d.x + WHITE * np.random
                                           .default_rng(s + 9).standard_normal(len(d)))
                        .assign(y_m=lambda d, s=seed: d.y + WHITE * np.random
                                .default_rng(s + 19).standard_normal(len(d)))
                        for seed in range(3)])
    assert white.rho < 0.05
    assert white.accuracy_scale == pytest.approx(WHITE / 0.5, rel=0.15)


def test_it_reads_how_slow_the_courses_errors_are_and_widens_its_sigma_by_that_alone():
    logs = [drive(seed, course=True) for seed in range(3)]
    got = course_errors(logs)
    assert got.step == pytest.approx(expected(1.0, COURSE_WHITE, COURSE_DRIFT), rel=0.1)
    assert got.sill == pytest.approx(np.mean([expected(s, COURSE_WHITE, COURSE_DRIFT)
                                              for s in COURSE_SILL_S]), rel=0.1)
    assert got.widening == pytest.approx(np.sqrt((1 + got.rho) / (1 - got.rho)))
    assert got.widening > 2.0
    # what it reads is the course less the gyro's turn: a gyro reading twice the turn swamps it
    wrong = [d.assign(r_m=0.1) for d in logs]
    assert course_errors(wrong).sill > 10 * got.sill
    assert receiver_scales(logs) == pytest.approx((fix_errors(logs).accuracy_scale,
                                                   got.widening), rel=1e-12)


def test_it_reads_no_truth_and_a_gap_or_a_missing_velocity_is_no_lag():
    log = drive(0)
    blind = log.drop(columns=["x", "y", "psi"])
    assert fix_errors(blind) == fix_errors(log)
    moved = log.assign(x=log.x + 5.0, psi=0.0)
    assert fix_errors(moved) == fix_errors(log)
    # a gap of 100 s in the fixes: the two sides are two runs, no pair straddles it
    gap = log.copy()
    gap.loc[1000:1099, ["x_m", "y_m"]] = np.nan
    pieces = [log.iloc[:1000], log.iloc[1100:]]
    split, apart = fix_errors(gap), fix_errors(pieces)
    assert split.pairs == apart.pairs == 1898
    assert (split.step, split.sill) == pytest.approx((apart.step, apart.sill), rel=1e-12)
    # a fix without a velocity breaks the integral: the runs on its two sides pair no more
    d, run = offsets(log.t.to_numpy(), log[["x_m", "y_m"]].to_numpy(),
                     log[["ve_m", "vn_m"]].to_numpy().copy())
    assert (run == 0).all()
    v = log[["ve_m", "vn_m"]].to_numpy().copy()
    v[500] = np.nan
    _, run = offsets(log.t.to_numpy(), log[["x_m", "y_m"]].to_numpy(), v)
    assert run[499] == 0 and run[500] == 1 and run[501] == 2 and run[-1] == 2


def test_a_log_it_cannot_read_is_one_line():
    with pytest.raises(LboError, match=r"^the fixes' variogram reads .*: log 0 has no ve_m, "
                                       r"vn_m column$"):
        fix_errors(drive(0).drop(columns=["ve_m", "vn_m"]))
    with pytest.raises(LboError, match=r"needs runs of fixes with a velocity over 30 s or more: "
                                       r"the logs give 11 pairs of consecutive fixes and 2 "
                                       r"over 10, 20, 30 s$"):
        fix_errors(drive(0, fixes=12))
    # the setting's own line names the field and the choices
    learn = OmegaConf.create({"epochs": 1, "segment_s": 10.0, "lr": 0.1,
                              "receiver_noise": "fixed"})
    with pytest.raises(LboError, match=r"^learn.receiver_noise must be one of \['learned', "
                                       r"'variogram'\], got 'fixed'$"):
        Settings.from_cfg(learn)


@pytest.mark.parametrize("path, group", [("conf/realdrive.yaml", "learn"),
                                         ("conf/receiver_study.yaml", "learn"),
                                         ("conf/model/gyro_ekf.yaml", None)])
def test_every_command_that_fits_the_gyro_ekf_takes_the_setting(path, group):
    cfg = OmegaConf.load(path)
    learn = cfg[group] if group else cfg
    assert Settings.from_cfg(learn).kwargs(0.02)["receiver_noise"] == "learned"  # the default
    assert Settings.from_cfg(learn).kwargs(0.02)["hold"] == ()  # nothing held by default
    learn.receiver_noise = "variogram"
    learn.hold = ["q_position", "course_lever"]
    assert Settings.from_cfg(learn).kwargs(0.02)["receiver_noise"] == "variogram"
    assert Settings.from_cfg(learn).kwargs(0.02)["hold"] == ("q_position", "course_lever")


@pytest.mark.parametrize("hold, line", [
    (["q_pos"], "learn.hold: expected names among q_position, q_heading, gyro_sigma, "
                "bias_walk, accuracy_scale, velocity_scale, course_lever, drift_sigma, "
                "drift_tau, speed_scale, gyro_scale, got 'q_pos'"),
    ("q_position", "learn.hold: expected a list of the gyro EKF's noise names, got "
                   "'q_position'"),
    ([1], "learn.hold: expected a list of the gyro EKF's noise names, got [1]")])
def test_a_hold_that_names_no_noise_is_one_line(hold, line):
    learn = OmegaConf.create({"epochs": 1, "segment_s": 10.0, "lr": 0.1, "hold": hold})
    with pytest.raises(LboError, match=f"^{re.escape(line)}$"):
        Settings.from_cfg(learn)


def test_a_hold_is_checked_against_the_noises_the_fit_learns_before_any_run():
    base = {"epochs": 1, "segment_s": 10.0, "lr": 0.1}
    with pytest.raises(LboError, match=r"^model.hold: drift_sigma is not a noise this fit "
                                       r"learns \(it learns q_position, .*, course_lever; "
                                       r"drift_sigma and drift_tau with model.drift=true, "
                                       r"speed_scale and gyro_scale with model.scales=true\)$"):
        Settings.from_cfg(OmegaConf.create({**base, "hold": ["drift_sigma"]}), "model")
    drift = Settings.from_cfg(OmegaConf.create({**base, "drift": True, "hold": ["drift_sigma"]}))
    assert drift.hold == ("drift_sigma",)
    every = ["q_position", "q_heading", "gyro_sigma", "bias_walk", "course_lever"]
    with pytest.raises(LboError, match=r"^learn.hold: every noise this fit learns is held or "
                                       r"set by its logs \(.*\): nothing is left to learn$"):
        Settings.from_cfg(OmegaConf.create({**base, "receiver_noise": "variogram",
                                            "hold": every}))
    # one left to learn (the receiver's factors), or no epoch to learn in: taken
    assert Settings.from_cfg(OmegaConf.create({**base, "hold": every})).hold == tuple(every)
    assert Settings.from_cfg(OmegaConf.create({**base, "epochs": 0, "receiver_noise":
                                               "variogram", "hold": every})).epochs == 0


def test_a_fit_holds_only_noises_its_filter_carries_and_leaves_one_to_learn():
    """Checked before any step: a drift's noise without the drift, and every noise held."""
    log = gyro_drive.draw(0).drop(columns=["x", "y", "psi"])
    start = GyroNoise.from_q(np.diag([0.0667**2, 0.0667**2, 0.00113**2]))
    R = np.diag([1.0, 1.0, 0.0174**2])
    with pytest.raises(LboError, match=r"^hold: drift_sigma is not a noise of this filter \(it "
                                       r"carries q_position, .*, course_lever\)$"):
        gyro_fit.fit(log, log, gyro_drive.VEHICLE, R, start, progress=None,
                     objective="innovations", hold=["drift_sigma"])
    every = [f.name for f in dataclasses.fields(start) if getattr(start, f.name) is not None]
    with pytest.raises(LboError, match=r"^hold: every noise of the filter is held or set by its "
                                       r"logs \(.*\): nothing is left to learn$"):
        gyro_fit.fit(log, log, gyro_drive.VEHICLE, R, start, progress=None,
                     objective="innovations", hold=every)


@pytest.mark.slow  # a fit: about 5 s
def test_the_fit_keeps_the_factors_the_receiver_calls_for_and_what_it_holds_and_learns_the_rest():
    log = gyro_drive.draw(0).drop(columns=["x", "y", "psi"])  # no truth to read
    start = GyroNoise.from_q(np.diag([0.0667**2, 0.0667**2, 0.00113**2]))
    R = np.diag([1.0, 1.0, 0.0174**2])
    fitted = gyro_fit.fit(log, log, gyro_drive.VEHICLE, R, start, epochs=1, segment=500,
                          progress=None, objective="innovations", receiver_noise="variogram",
                          hold=["course_lever"])
    accuracy, velocity = receiver_scales(log)
    assert fitted.start == dataclasses.replace(start, accuracy_scale=accuracy,
                                               velocity_scale=velocity)
    assert accuracy != pytest.approx(1.0, abs=0.05) and velocity != pytest.approx(1.0, abs=0.05)
    # a step was taken and kept: the other noises moved, these two stayed (to the rounding
    # of the log they are held as; this fails if the fit frees them, which moves them too)
    assert fitted.best_epoch == 1
    assert fitted.noise.q_position != pytest.approx(start.q_position, rel=1e-3)
    assert (fitted.noise.accuracy_scale, fitted.noise.velocity_scale) == pytest.approx(
        (accuracy, velocity), rel=1e-12)
    # held: where it started (a noise learned moves in that step, as q_position did)
    assert fitted.noise.course_lever == pytest.approx(start.course_lever, rel=1e-12)
    assert fitted.noise.q_heading != pytest.approx(start.q_heading, rel=1e-3)


@pytest.mark.slow  # a fit: about 5 s
def test_observe_adapt_reads_the_receivers_factors_from_the_log_it_filters(tmp_path):
    """``adapt_receiver_noise=variogram``: the fit adapt=true makes sets the receiver's factors
    from the log itself (the truth in it unread) and says so; without adapt, or with a value
    not known, one line and no output."""
    log = gyro_drive.draw(0)
    log.to_csv(tmp_path / "log.csv", index=False)
    out = tmp_path / "est.csv"
    args = [f"input={tmp_path / 'log.csv'}", "observer=gyro", f"output={out}"]
    done = observe(*args, "adapt=true", "adapt_epochs=1", "adapt_receiver_noise=variogram",
                   cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    assert ("adapting: the gyro EKF's noise to this log's innovations, the receiver's noise by "
            "its variogram, 1 epochs") in done.stdout
    kept = re.search(r"accuracy_scale=([0-9.e-]+), velocity_scale=([0-9.e-]+)", done.stdout)
    accuracy, velocity = receiver_scales(log.drop(columns=["x", "y", "psi"]))
    assert (float(kept[1]), float(kept[2])) == pytest.approx((accuracy, velocity), rel=1e-9)
    assert out.is_file()
    out.unlink()
    for extra, line in ((["adapt_receiver_noise=variogram"],
                         "adapt_receiver_noise: how the fit adapt=true makes for observer=gyro "
                         "finds the receiver's factors; pass both with it"),
                        (["adapt=true", "adapt_receiver_noise=fixed"],
                         "adapt_receiver_noise must be one of ['learned', 'variogram'], got "
                         "'fixed'")):
        assert one_line_error(observe(*args, *extra, cwd=tmp_path)) == f"error: {line}"
        assert not out.exists()
