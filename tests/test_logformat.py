"""Logs as they arrive: column names, units, steering ratio, heading convention, lat/lon."""

from __future__ import annotations

import math
import re

import numpy as np
import pandas as pd
import pymap3d
import pytest

from helpers import compose_cfg, observed
from lbo.core.errors import LboError
from lbo.logs.formats import LogFormat, Origin, to_local
from lbo.logs.units import check_conventions

COLUMNS = ["t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"]
ORIGIN = Origin(48.7758, 2.2886)  # near Paris


@pytest.fixture(scope="module")
def test_set(smoke_data) -> pd.DataFrame:
    return pd.read_parquet(smoke_data / "test.parquet")


@pytest.fixture(scope="module")
def plain(test_set) -> pd.DataFrame:
    """A hairpin at alpha = 2, in lbo's form."""
    g = test_set[(test_set["traj"] == 1) & (test_set["alpha"] == 2.0)].sort_values("k")
    return g[COLUMNS].reset_index(drop=True)


def as_logged(plain: pd.DataFrame) -> pd.DataFrame:
    """The same drive as a logger writes it: lat/lon, km/h, compass degrees (from the local
    north at each position), the steering wheel's angle in degrees (ratio 15.5), its own
    column names, a column lbo ignores."""
    lat, lon, _ = pymap3d.enu2geodetic(plain["x_m"], plain["y_m"], 0.0, ORIGIN.lat,
                                       ORIGIN.lon, 0.0)
    lat_t, lon_t, _ = pymap3d.enu2geodetic(plain["x"], plain["y"], 0.0, ORIGIN.lat,
                                           ORIGIN.lon, 0.0)
    compass = lambda psi, la, lo: np.degrees(  # noqa: E731
        np.pi / 2 - ORIGIN.heading_at(psi, la, lo)) % 360
    return pd.DataFrame({"time_s": plain["t"], "gnss_lat": lat, "gnss_lon": lon,
                         "gnss_heading_deg": compass(plain["psi_m"], lat, lon),
                         "speed_kmh": plain["V"] * 3.6,
                         "steering_wheel_deg": np.degrees(plain["delta"]) * 15.5,
                         "ref_lat": lat_t, "ref_lon": lon_t,
                         "ref_heading_deg": compass(plain["psi"], lat_t, lon_t), "rpm": 2000.0})


LOGGED = ["columns.t=time_s", "columns.lat=gnss_lat", "columns.lon=gnss_lon",
          "columns.psi_m=gnss_heading_deg", "columns.V=speed_kmh",
          "columns.delta=steering_wheel_deg", "columns.lat_true=ref_lat",
          "columns.lon_true=ref_lon", "columns.psi=ref_heading_deg", "units.V=kmh",
          "units.psi=deg", "units.delta=deg", "steering_ratio=15.5", "heading=compass"]


# ------------------------------------------------------------------------------ geodesy


@pytest.mark.parametrize("lat, d_lat, d_lon, north, east", [
    # WGS84 lengths of 0.001 degree: of latitude 110.574 m and of longitude 111.320 m at the
    # equator; 111.133 m and 78.847 m at 45 degrees
    (0.0, 0.001, 0.0, 110.574, 0.0), (0.0, 0.0, 0.001, 0.0, 111.320),
    (45.0, 0.001, 0.0, 111.133, 0.0), (45.0, 0.0, 0.001, 0.0, 78.847),
])
def test_lat_lon_become_metres_east_and_north_as_published(lat, d_lat, d_lon, north, east):
    origin = Origin(lat - d_lat / 2, 10.0 - d_lon / 2)
    e, n = to_local(np.array([origin.lat, lat + d_lat / 2]),
                    np.array([origin.lon, 10.0 + d_lon / 2]), origin)
    assert e[0] == pytest.approx(0, abs=1e-9) and n[0] == pytest.approx(0, abs=1e-9)
    assert e[1] == pytest.approx(east, abs=2e-3) and n[1] == pytest.approx(north, abs=2e-3)
    back = origin.to_geodetic(e, n)
    np.testing.assert_allclose(back, [[origin.lat, lat + d_lat / 2],
                                      [origin.lon, 10.0 + d_lon / 2]], atol=1e-10)


# ------------------------------------------------------------------ a logger's log, mapped


def test_a_loggers_log_gives_the_estimates_of_the_same_log_in_lbos_form(tmp_path, plain):
    plain.to_csv(tmp_path / "plain.csv", index=False)
    as_logged(plain).to_csv(tmp_path / "logged.csv", index=False)
    want = observed(tmp_path / "plain.csv", tmp_path / "want.csv")
    got = observed(tmp_path / "logged.csv", tmp_path / "est.csv", *LOGGED)
    np.testing.assert_allclose(got["rmse"], want["rmse"], rtol=1e-6)
    a, b = pd.read_csv(tmp_path / "want.csv"), pd.read_csv(tmp_path / "est.csv")
    # metres east/north of the first fix: the plain log's frame shifted, and turned by the
    # tangent planes' difference over the few metres between the two origins (< 0.1 mm)
    shift = plain[["x_m", "y_m"]].iloc[0].to_numpy()
    np.testing.assert_allclose(b[["x", "y"]] + shift, a[["x", "y"]], atol=1e-4)
    # headings in the first fix's frame: the plain log's, turned by the meridians between
    # the two origins (1e-6 rad over those few metres)
    first = Origin(*(float(as_logged(plain)[c].iloc[0]) for c in ("gnss_lat", "gnss_lon")))
    np.testing.assert_allclose(b["psi"], first.heading_from(a["psi"], ORIGIN.lat, ORIGIN.lon),
                               atol=1e-8)
    # the estimate in degrees too, where the log's positions were
    lat, lon, _ = pymap3d.enu2geodetic(a["x"], a["y"], 0.0, ORIGIN.lat, ORIGIN.lon, 0.0)
    np.testing.assert_allclose(b["lat"], lat, atol=1e-9)  # 0.1 mm
    np.testing.assert_allclose(b["lon"], lon, atol=1e-9)


def test_observe_says_how_it_read_the_log(tmp_path, plain, capsys):
    as_logged(plain).to_csv(tmp_path / "logged.csv", index=False)
    observed(tmp_path / "logged.csv", tmp_path / "est.csv", *LOGGED)
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("read as:"))
    assert "V <- speed_kmh" in line and "V in kmh" in line and "steering ratio 15.5" in line
    assert "compass headings" in line and "lat/lon -> metres east/north of 48.77" in line


def test_format_apply_keeps_lbos_form_untouched(plain):
    out, origin = LogFormat().apply(plain)
    assert origin is None and out is not plain
    pd.testing.assert_frame_equal(out, plain)
    assert LogFormat().is_plain and LogFormat(units={"V": "mps"}).is_plain
    assert not LogFormat(units={"V": "mph"}).is_plain


def test_units_and_conventions_convert_as_documented():
    df = pd.DataFrame({"t": [0.0], "x_m": [1.0], "y_m": [2.0], "psi_m": [90.0],
                       "V": [36.0], "delta": [180.0]})
    out, _ = LogFormat(units={"V": "kmh", "psi": "deg", "delta": "deg"},
                       steering_ratio=2.0).apply(df)
    assert out["V"][0] == pytest.approx(10.0)
    assert out["psi_m"][0] == pytest.approx(math.pi / 2)
    assert out["delta"][0] == pytest.approx(math.pi / 2)
    mph, _ = LogFormat(units={"V": "mph"}).apply(df.assign(V=10.0))
    assert mph["V"][0] == pytest.approx(4.4704)
    # compass: 0 is north (pi/2 in lbo's), 90 is east (0 in lbo's), 180 south, 270 west
    bearings = df.loc[[0] * 4].assign(psi_m=[0.0, 90.0, 180.0, 270.0])
    out, _ = LogFormat(units={"psi": "deg"}, heading="compass").apply(bearings)
    np.testing.assert_allclose(out["psi_m"], [math.pi / 2, 0.0, -math.pi / 2, math.pi],
                               atol=1e-12)


# --------------------------------------------------------------- suspicious units: a hint


@pytest.mark.parametrize("edit, hint", [
    (lambda d: d.assign(V=d["V"] * 3.6), "column 'V' looks like km/h: it travels 3."),
    (lambda d: d.assign(V=d["V"] / 0.44704), "column 'V' looks like mph"),
    (lambda d: d.assign(psi_m=np.angle(np.exp(1j * (np.pi / 2 - d["psi_m"])))),
     "(read as heading=enu), but its mirror image does: pass heading=compass"),
])
def test_a_speed_or_heading_that_contradicts_the_fixes_is_refused(tmp_path, plain, edit, hint):
    log = tmp_path / "log.csv"
    edit(plain).to_csv(log, index=False)
    with pytest.raises(LboError, match=re.escape(hint)):
        observed(log, tmp_path / "est.csv")
    assert not (tmp_path / "est.csv").exists()


def test_a_compass_log_read_as_enu_the_other_way_round(tmp_path, plain):
    log = tmp_path / "log.csv"
    plain.to_csv(log, index=False)
    with pytest.raises(LboError, match=re.escape("(read as heading=compass), but its mirror "
                                                 "image does: pass heading=enu")):
        observed(log, tmp_path / "est.csv", "heading=compass")


def test_no_simulated_log_looks_suspicious(test_set, smoke_data):
    """Every test manoeuvre at every alpha (0 to 6: fixes up to 6 m off) and the example log
    pass the convention checks."""
    from lbo.core.paths import EXAMPLE_LOG

    for _, g in test_set.groupby(["traj", "alpha"]):
        g = g.sort_values("k")
        check_conventions(g["t"].to_numpy(), g[["x_m", "y_m", "psi_m"]].to_numpy(),
                          g[["V", "delta"]].to_numpy())
    ex = pd.read_csv(EXAMPLE_LOG)
    check_conventions(ex["t"].to_numpy(), ex[["x_m", "y_m", "psi_m"]].to_numpy(),
                      ex[["V", "delta"]].to_numpy())


# ------------------------------------------------------------------ bad settings: one line


@pytest.mark.parametrize("override, message", [
    ("units.V=knots", "units.V must be one of mps, kmh, mph, got 'knots'"),
    ("units.psi=grad", "units.psi must be one of rad, deg, got 'grad'"),
    ("steering_ratio=0", "steering_ratio must be a number > 0"),
    ("steering_ratio=fast", "steering_ratio must be a number > 0"),
    ("heading=north", "heading must be enu (counter-clockwise from east) or compass"),
    ("columns.V=speed", "columns.V=speed: no column 'speed' in the log (found t, x_m"),
    ("+columns.speed=V", "columns.speed: unknown field; expected one of t, x_m"),
    ("+units.t=ms", "units.t: unknown field; expected one of V, psi, delta"),
])
def test_bad_format_settings_are_one_line_and_write_nothing(tmp_path, plain, override, message):
    log = tmp_path / "log.csv"
    plain.to_csv(log, index=False)
    with pytest.raises(LboError, match=re.escape(message)):
        observed(log, tmp_path / "est.csv", override)
    assert not (tmp_path / "est.csv").exists()


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.drop(columns=["gnss_lon"]), "column 'lat' without 'lon'"),
    (lambda d: d.assign(x_m=0.0, y_m=0.0), "both lat/lon and x_m/y_m"),
    (lambda d: d.assign(gnss_lat=d["gnss_lat"] * 1e5), "row 0: lat=4.87758e+06 is outside "
     "[-90, 90]; lat is in degrees"),
    (lambda d: d.assign(speed_kmh="fast"), "column 'V' is not numeric"),
])
def test_bad_geodetic_logs_are_one_line(tmp_path, plain, edit, message):
    log = tmp_path / "log.csv"
    edit(as_logged(plain)).to_csv(log, index=False)
    overrides = [o for o in LOGGED if "lon=" not in o or "gnss_lon" in pd.read_csv(log).columns]
    with pytest.raises(LboError, match=re.escape(message)):
        observed(log, tmp_path / "est.csv", *overrides)
    assert not (tmp_path / "est.csv").exists()


# ----------------------------------------------------------------------------- data=logs


def test_data_logs_reads_a_loggers_logs_as_their_plain_twins(test_set, tmp_path):
    from lbo.logs import sets as logs

    for kind in ("plain", "logged"):
        for part in ("train", "val", "test"):
            (tmp_path / kind / part).mkdir(parents=True)
    for (traj, alpha), g in test_set.groupby(["traj", "alpha"]):
        part = "val" if alpha == 1.0 else "test" if alpha == 3.0 else "train"
        if alpha > 3 and part == "train":
            continue
        log = g.sort_values("k")[COLUMNS].reset_index(drop=True)
        log = log - np.r_[[0.0], log[["x_m", "y_m"]].iloc[0].to_numpy(), [0.0] * 6] * \
            np.r_[0, 1, 1, 0, 0, 0, 1, 1, 0]  # plain logs start where the lat/lon origin is
        log.to_csv(tmp_path / "plain" / part / f"m{traj}_a{alpha:g}.csv", index=False)
        as_logged(log).to_csv(tmp_path / "logged" / part / f"m{traj}_a{alpha:g}.csv",
                              index=False)

    def sets(kind, *more):
        cfg = compose_cfg("train", ["experiment=smoke", "data=logs", "data.run_in=100",
                                    *(f"data.{p}=[{tmp_path / kind / p}]"
                                      for p in ("train", "val", "test")),
                                    f"data.root={tmp_path / 'data'}", *more])
        return logs.build(logs.spec_from_cfg(cfg), progress=False)[1]

    want = sets("plain")
    got = sets("logged", *(f"data.{o}" for o in LOGGED))
    for part in want:
        cols = ["x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"]
        np.testing.assert_allclose(got[part][cols].to_numpy(), want[part][cols].to_numpy(),
                                   atol=1e-6)
    with pytest.raises(LboError, match=re.escape("data.units.V must be one of mps, kmh, mph")):
        sets("logged", "data.units.V=kn")
