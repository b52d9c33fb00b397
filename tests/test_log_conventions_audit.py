"""Issue 41, items 13-15: a log's heading conventions near a pole, while reversing, and
unwrapped.

13. Compass headings with lat/lon fixes near a pole: each is clockwise from the local north
    at its own fix, which leans from the first fix's north by the meridians' convergence.
14. A car reversing (V < 0) while facing south-east: its heading points against the motion,
    which is no sign of the other heading convention.
15. A heading in rad that a logger accumulates (past 2 pi, lap after lap) is not degrees:
    degrees are told by how fast the heading turns, not by its range.

Each log is built here, simulated with lbo's kinematic model and measured at alpha = 1
(the paper's sigmas: 1 m, 1 m, 17.4 mrad), and every estimate is scored against the truth
of the simulation, not against truth columns read back through the same conversion.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from helpers import observed
from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.logs.checks import check_samples
from lbo.logs.formats import LogFormat, Origin
from lbo.logs.units import check_conventions
from lbo.sim.vehicle import simulate

DT = 0.02
SIGMA = np.array([1.0, 1.0, 17.4e-3])  # the paper's measurement sigmas at alpha = 1


def drive(psi0: float, v: np.ndarray, delta: np.ndarray, seed: int = 0
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Truth z (T, 3) (psi continuous), fixes m (T, 3) with noise, inputs u (T, 2), from
    (0, 0, psi0) under speeds ``v`` (T,) and steering ``delta`` (T,); the first fix exact
    (it is a geodetic log's origin)."""
    u = np.stack([v, delta], -1)
    z = simulate(np.array([[0.0, 0.0, psi0]]), u[None], DT, 2.7)[0]
    m = z + np.random.default_rng(seed).standard_normal(z.shape) * SIGMA
    m[0] = z[0]
    return z, m, u


def frame(z: np.ndarray, m: np.ndarray, u: np.ndarray) -> pd.DataFrame:
    """A log in lbo's form, its measured heading wrapped as a logger writes it."""
    return pd.DataFrame({"t": np.arange(len(z)) * DT, "x_m": m[:, 0], "y_m": m[:, 1],
                         "psi_m": wrap_angle(m[:, 2]), "V": u[:, 0], "delta": u[:, 1],
                         "x": z[:, 0], "y": z[:, 1], "psi": wrap_angle(z[:, 2])})


def observe(tmp_path: Path, log: pd.DataFrame, *overrides: str, name: str = "log"
            ) -> tuple[dict, pd.DataFrame]:
    """``python -m lbo.observe observer=ekf`` on ``log``: its result and its output."""
    path, out = tmp_path / f"{name}.csv", tmp_path / f"{name}_est.csv"
    log.to_csv(path, index=False)
    result = observed(path, out, *overrides)
    return result, pd.read_csv(out)


def errors(est: pd.DataFrame, z: np.ndarray) -> np.ndarray:
    """RMSE (3,) of the valid estimates against the simulated truth z (T, 3)."""
    ok = est["valid"].to_numpy(bool)
    e = est[["x", "y", "psi"]].to_numpy()[ok] - z[ok]
    e[:, 2] = wrap_angle(e[:, 2])
    return np.sqrt(np.mean(e ** 2, axis=0))


# ------------------------------------------------------------ 13. meridian convergence


POLE = Origin(89.98, 10.0)  # 2.2 km from the north pole


def convergence(lat: np.ndarray, lon: np.ndarray, origin: Origin) -> np.ndarray:
    """The angle (rad, counter-clockwise) from the y axis of ``origin``'s ENU frame to the
    local north at (lat, lon), projected onto the origin's tangent plane: the north at a
    point is (-sin lat cos lon, -sin lat sin lon, cos lat) in ECEF on the ellipsoid too
    (geodetic latitude), and the frame's east and north are the origin's. A closed form, not
    the code's route (pymap3d's rotations)."""
    p, p0 = np.radians(lat), np.radians(origin.lat)
    dl = np.radians(lon - origin.lon)
    return np.arctan2(np.sin(p) * np.sin(dl),
                      np.sin(p0) * np.sin(p) * np.cos(dl) + np.cos(p0) * np.cos(p))


@pytest.fixture(scope="module")
def polar():
    """A 60 s drive 2.2 km from the pole, bending from east to north-east at 10 m/s: 600 m
    across meridians that turn by up to 0.3 rad. Returns the truth, the log with lat/lon and
    compass bearings in degrees (each from the local north at its own position), and the
    fixes' convergence."""
    t = np.arange(3000) * DT
    z, m, u = drive(0.0, np.full(len(t), 10.0), 0.02 * np.sin(2 * np.pi * t / 30))
    lat, lon = POLE.to_geodetic(m[:, 0], m[:, 1])
    lat_t, lon_t = POLE.to_geodetic(z[:, 0], z[:, 1])
    c_fix, c_true = convergence(lat, lon, POLE), convergence(lat_t, lon_t, POLE)
    # a bearing from the local north: the frame's heading less the north's own turn there
    bearing = lambda psi, c: np.degrees(np.pi / 2 + c - psi) % 360  # noqa: E731
    log = pd.DataFrame({"t": t, "lat": lat, "lon": lon, "heading": bearing(m[:, 2], c_fix),
                        "V": u[:, 0], "delta": u[:, 1], "lat_true": lat_t, "lon_true": lon_t,
                        "heading_true": bearing(z[:, 2], c_true)})
    return z, m, log, c_fix


COMPASS = ["columns.psi_m=heading", "columns.psi=heading_true", "units.psi=deg",
           "heading=compass"]


def test_the_scenario_turns_the_meridians_by_a_third_of_a_radian(polar):
    *_, c_fix = polar
    assert 0.25 < np.abs(c_fix).max() < 0.35


def test_a_compass_heading_near_a_pole_is_turned_by_the_north_at_its_own_fix(polar):
    z, m, log, _ = polar
    fmt = LogFormat(columns={"psi_m": "heading", "psi": "heading_true"},
                    units={"psi": "deg"}, heading="compass")
    out, origin = fmt.apply(log)
    assert (origin.lat, origin.lon) == pytest.approx((POLE.lat, POLE.lon), abs=1e-9)
    # the measured and the true headings in the frame's axes, as the simulation drew them
    np.testing.assert_allclose(wrap_angle(out["psi_m"] - m[:, 2]), 0.0, atol=1e-6)
    np.testing.assert_allclose(wrap_angle(out["psi"] - z[:, 2]), 0.0, atol=1e-6)
    # and back: the frame's heading as the local one at each point
    back = origin.heading_at(out["psi"], log["lat_true"], log["lon_true"])
    np.testing.assert_allclose(wrap_angle(np.pi / 2 - np.radians(log["heading_true"]) - back),
                               0.0, atol=1e-6)


def test_the_estimate_near_a_pole_is_as_good_as_anywhere(tmp_path, polar):
    z, m, log, _ = polar
    result, est = observe(tmp_path, log, *COMPASS)
    truth = errors(est, z)
    # the heading against the simulation's truth: the paper's EKF at alpha = 1 (4.1 mrad on
    # its test set), not the 0.3 rad of the meridians' turn
    assert truth[2] < 0.01, truth
    assert truth[0] < 0.5 and truth[1] < 0.5, truth
    # and the printed RMSE, from the log's own truth columns, says the same
    np.testing.assert_allclose(result["rmse"], truth, rtol=1e-3)


def test_an_enu_heading_near_a_pole_is_turned_too(polar):
    """An ENU heading with lat/lon fixes is counter-clockwise from the local east at its fix,
    which the meridians turn by as much as the north."""
    _, m, log, _ = polar
    enu = log.assign(heading=np.pi / 2 - np.radians(log["heading"]))
    out, _ = LogFormat(columns={"psi_m": "heading"}).apply(enu.drop(columns="heading_true"))
    np.testing.assert_allclose(wrap_angle(out["psi_m"] - m[:, 2]), 0.0, atol=1e-6)


# --------------------------------------------------------------------------- 14. reversing


@pytest.fixture(scope="module")
def reversing():
    """40 s reversing at 8 m/s facing south-east (V = -8, psi = -pi/4, swaying by 0.1 rad),
    and the same path driven forwards facing north-west (psi + pi, V = 8, delta negated: the
    same positions and yaw rate), with the same noise."""
    t = np.arange(2000) * DT
    delta = 0.01 * np.sin(2 * np.pi * t / 20)
    back = drive(-np.pi / 4, np.full(len(t), -8.0), delta)
    ahead = drive(3 * np.pi / 4, np.full(len(t), 8.0), -delta)
    np.testing.assert_allclose(back[0][:, :2], ahead[0][:, :2], atol=1e-9)
    return back, ahead


def test_a_car_reversing_passes_the_check_and_is_estimated_as_well_as_driving_ahead(
        tmp_path, reversing):
    (z_b, m_b, u_b), (z_a, m_a, u_a) = reversing
    got, est_b = observe(tmp_path, frame(z_b, m_b, u_b), name="back")
    want, est_a = observe(tmp_path, frame(z_a, m_a, u_a), name="ahead")
    rmse_b, rmse_a = errors(est_b, z_b), errors(est_a, z_a)
    assert (rmse_b <= 1.2 * rmse_a).all(), (rmse_b, rmse_a)
    assert rmse_b[2] < 0.01
    np.testing.assert_allclose(got["rmse"], rmse_b, rtol=1e-6)


def test_a_reversing_log_is_never_told_to_switch_to_compass(reversing):
    (z, m, u), _ = reversing
    log = frame(z, m, u)
    t, mm = log["t"].to_numpy(), log[["x_m", "y_m", "psi_m"]].to_numpy()
    check_conventions(t, mm, u)
    # an unsigned speed while reversing: the heading lies along the path, backwards
    check_conventions(t, mm, np.abs(u))


def test_a_reversing_compass_log_read_as_enu_is_told_compass_and_then_runs(tmp_path):
    """Reversing round bends (V < 0), with compass bearings: read as ENU, the hint names the
    convention in which the heading points where the car moves; following it, the estimate
    is as good as the ENU log's."""
    t = np.arange(3000) * DT
    z, m, u = drive(0.3, np.full(len(t), -8.0), 0.08 * np.sin(2 * np.pi * t / 25))
    enu = frame(z, m, u)
    compass = enu.assign(psi_m=wrap_angle(np.pi / 2 - enu["psi_m"]),
                         psi=wrap_angle(np.pi / 2 - enu["psi"]))
    with pytest.raises(LboError, match=re.escape("(read as heading=enu), but its mirror image "
                                                 "does: pass heading=compass")):
        observe(tmp_path, compass, name="compass_as_enu")
    _, followed = observe(tmp_path, compass, "heading=compass", name="compass")
    _, plain = observe(tmp_path, enu, name="enu")
    np.testing.assert_allclose(errors(followed, z), errors(plain, z), rtol=1e-6)
    assert errors(followed, z)[2] < 0.01


# ----------------------------------------------------------------- 15. unwrapped radians


@pytest.fixture(scope="module")
def laps():
    """60 s of circles at 10 m/s turning at 0.4 rad/s, logged by a logger that accumulates
    its heading: from 86 rad (the laps before) to 110 rad."""
    t = np.arange(3000) * DT
    z, m, u = drive(86.0, np.full(len(t), 10.0), np.full(len(t), np.arctan(0.4 * 2.7 / 10)))
    assert 109 < z[-1, 2] < 111
    unwrapped = frame(z, m, u).assign(psi_m=m[:, 2], psi=z[:, 2])
    return z, unwrapped


def test_an_unwrapped_heading_in_rad_runs_as_the_wrapped_one(tmp_path, laps):
    z, unwrapped = laps
    got, est = observe(tmp_path, unwrapped, name="unwrapped")
    want, _ = observe(tmp_path, unwrapped.assign(psi_m=wrap_angle(unwrapped["psi_m"]),
                                                  psi=wrap_angle(unwrapped["psi"])),
                      name="wrapped")
    np.testing.assert_allclose(got["rmse"], want["rmse"], rtol=1e-6)
    assert errors(est, z)[2] < 0.01


def refused_then_run_in_degrees(tmp_path, degrees, z, message: str, name: str) -> None:
    """A log with headings in degrees is refused with ``message``, and the advice it gives
    (units.psi=deg) runs it with the heading as good as in rad."""
    with pytest.raises(LboError, match=message):
        observe(tmp_path, degrees, name=name)
    _, est = observe(tmp_path, degrees, "units.psi=deg", name=f"{name}_deg")
    assert errors(est, z)[2] < 0.01


def test_the_same_heading_in_degrees_is_refused_and_units_deg_runs_it(tmp_path, laps):
    z, unwrapped = laps
    degrees = unwrapped.assign(psi_m=np.degrees(unwrapped["psi_m"]),
                               psi=np.degrees(unwrapped["psi"]))
    refused_then_run_in_degrees(tmp_path, degrees, z, r"column 'psi_m' looks like degrees: "
                                r"read as rad it turns faster than 2 rad/s .*; give headings "
                                r"in rad, or pass units\.psi=deg$", "degrees")


def test_degrees_on_a_straight_road_are_told_by_where_the_car_moves(tmp_path):
    """Driving straight with a good heading (1.7 mrad of noise, 0.1 deg), a heading in
    degrees barely turns, even read as rad: the fixes tell it instead."""
    z, m, u = drive(-0.7, np.full(2000, 10.0), np.zeros(2000))
    m[:, 2] = z[:, 2] + np.random.default_rng(1).standard_normal(len(z)) * 1.7e-3
    degrees = frame(z, m, u).assign(psi_m=np.degrees(m[:, 2]), psi=np.degrees(z[:, 2]))
    refused_then_run_in_degrees(tmp_path, degrees, z, r"column 'psi_m' looks like degrees: "
                                r"it does not point where the fixes move, but read as degrees "
                                r"it does; give headings in rad, or pass units\.psi=deg",
                                "straight")


def test_observer_run_takes_unwrapped_rad_and_refuses_degrees(laps):
    z, unwrapped = laps
    m = unwrapped[["x_m", "y_m", "psi_m"]].to_numpy()
    u = unwrapped[["V", "delta"]].to_numpy()
    assert check_samples(m, u).all()
    with pytest.raises(LboError, match="column 'psi_m' looks like degrees"):
        check_samples(m * [1, 1, 180 / np.pi], u)


def test_no_simulated_heading_turns_too_fast_for_rad(smoke_data):
    """Every test manoeuvre at every alpha (heading noise up to 0.1 rad at alpha = 6), the
    example log (stop-and-go, fixes at 10 Hz) pass the rate check, truth and all."""
    from lbo.core.paths import EXAMPLE_LOG

    test = pd.read_parquet(smoke_data / "test.parquet")
    logs = [g.sort_values("k") for _, g in test.groupby(["traj", "alpha"])]
    logs.append(pd.read_csv(EXAMPLE_LOG))
    assert max(g["alpha"].max() for g in logs[:-1]) >= 6
    for g in logs:
        truth = g[["x", "y", "psi"]].to_numpy() if "psi" in g else None
        check_samples(g[["x_m", "y_m", "psi_m"]].to_numpy(), g[["V", "delta"]].to_numpy(),
                      truth=truth, t=g["t"].to_numpy())


def test_a_heading_that_turns_too_fast_in_rad_and_degrees_alike_is_no_heading(laps):
    """No reading helps a column of noise: the line says so, and advises no unit."""
    _, unwrapped = laps
    m = unwrapped[["x_m", "y_m", "psi_m"]].to_numpy()
    m[:, 2] = np.random.default_rng(2).uniform(-1e4, 1e4, len(m))
    with pytest.raises(LboError, match=r"^column 'psi_m' turns faster than 2 rad/s in \d+% of "
                                       r"its 0.5 s spans, read as rad and as degrees alike"):
        check_samples(m, unwrapped[["V", "delta"]].to_numpy())
