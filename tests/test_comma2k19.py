"""The comma2k19 reader (lbo.logs.comma2k19) on the shipped example segment: units, axes, the
fixes' latency, the truth's frame, the steering fit, the log's checks, and the reader of a
segment's original folder layout."""

from __future__ import annotations

from dataclasses import fields
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lbo.core.errors import LboError
from lbo.logs import comma2k19
from lbo.logs.io import check_log, check_period, check_steering
from lbo.sim.vehicle import Vehicle

DT = Vehicle().dt


@pytest.fixture(scope="module")
def segment() -> comma2k19.Segment:
    return comma2k19.example()


@pytest.fixture(scope="module")
def converted(segment: comma2k19.Segment) -> comma2k19.Converted:
    return comma2k19.to_log(segment)


@pytest.fixture(scope="module")
def log(converted: comma2k19.Converted) -> pd.DataFrame:
    return converted.log


def _truth_velocity(log: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """The truth's own velocity (east, north m/s), by differences of its positions."""
    return np.gradient(log["x"].to_numpy(), DT), np.gradient(log["y"].to_numpy(), DT)


def _fixes(log: pd.DataFrame) -> np.ndarray:
    return log["x_m"].notna().to_numpy()


def _over(values: np.ndarray, k: int) -> np.ndarray:
    """(T - k,) the sums of ``values * DT`` over each k steps (a rate integrated)."""
    c = np.concatenate([[0.0], np.cumsum(values) * DT])
    return c[k:-1] - c[:-k - 1]


def test_example_shapes_and_span(segment: comma2k19.Segment, log: pd.DataFrame) -> None:
    assert segment.position.shape == (1200, 3) and segment.position.dtype == np.float64
    assert segment.orientation.shape == (1200, 4) and segment.gyro.shape[1] == 3
    assert segment.fix.shape[1] == 6 and segment.speed.ndim == 1
    with pytest.raises(ValueError):  # read-only
        segment.speed[0] = 0.0
    # 60 s at 50 Hz over the span every stream covers; 10 Hz fixes, one per row at most
    assert 59.5 < log["t"].iloc[-1] < 60.0 and np.allclose(np.diff(log["t"]), DT)
    assert 570 <= _fixes(log).sum() <= len(segment.fix_t)
    assert log[["psi_m", "sx_m", "sy_m", "sv_m"]].isna().all().all()


def test_speeds_in_m_per_s_agree(log: pd.DataFrame) -> None:
    V = log["V"].to_numpy()
    assert 7.0 < V.min() and V.max() < 25.0 and np.median(V) > 15.0  # a highway, in m/s
    speed = np.hypot(*_truth_velocity(log))
    assert abs(np.median(V / speed - 1)) < 0.02  # CAN speed: 0.8% under the pose's
    fix = _fixes(log)
    fix_speed = np.hypot(log["ve_m"], log["vn_m"]).to_numpy()[fix]
    assert abs(np.median(fix_speed / speed[fix] - 1)) < 0.01
    assert np.max(np.abs(fix_speed / speed[fix] - 1)) < 0.05


def test_gyro_yaw_rate_turns_as_the_truth(log: pd.DataFrame) -> None:
    k = round(1.0 / DT)  # heading changes over 1 s: the gyro's white noise averaged
    psi = np.unwrap(log["psi"].to_numpy())
    turned = psi[k:] - psi[:-k]
    rate = _over(log["r_m"].to_numpy(), k)
    assert np.corrcoef(turned, rate)[0, 1] > 0.9  # counter-clockwise: the down axis negated
    assert abs(np.mean(rate - turned)) < 0.005  # a calibrated gyro (bias 0.6 mrad/s)


def test_latency_fitted_near_80_ms(segment: comma2k19.Segment,
                                   converted: comma2k19.Converted) -> None:
    assert "latency" in converted.fitted
    assert 0.05 <= converted.latency <= 0.11
    assert converted.rms < 0.7 < 1.2 < converted.rms_at_zero

    def rms(log: pd.DataFrame) -> float:
        f = _fixes(log)
        return float(np.sqrt(np.mean((log["x_m"][f] - log["x"][f]) ** 2
                                     + (log["y_m"][f] - log["y"][f]) ** 2)))

    at_zero = comma2k19.to_log(segment, steering=converted.steering, latency=0.0)
    assert at_zero.fitted == () and at_zero.latency == 0.0
    assert rms(converted.log) < 0.5 * rms(at_zero.log)


def test_truth_in_the_fixes_frame(converted: comma2k19.Converted, log: pd.DataFrame) -> None:
    f = _fixes(log)
    offset = np.hypot(log["x_m"] - log["x"], log["y_m"] - log["y"]).to_numpy()[f]
    assert offset.max() < 3.0 and np.sqrt(np.mean(offset**2)) < 0.7
    assert abs(converted.origin.lat - 37.721) < 1e-3 and abs(converted.origin.lon + 122.4723) < 1e-3
    assert np.hypot(log["x"].iloc[0], log["y"].iloc[0]) < 1.0  # the origin: the first pose
    # heading: counter-clockwise from east, along the truth's own course (north on this road)
    ve, vn = _truth_velocity(log)
    off = np.angle(np.exp(1j * (log["psi"].to_numpy() - np.arctan2(vn, ve))))
    assert np.sqrt(np.mean(off**2)) < 0.005
    assert abs(np.median(log["psi"]) - np.pi / 2) < 0.1
    assert 0.005 < abs(converted.boresight) < 0.05  # the EON turned on the windshield
    course = np.arctan2(log["vn_m"], log["ve_m"]).to_numpy()[f]  # from the fix's bearing
    assert np.sqrt(np.mean(np.angle(np.exp(1j * (course - log["psi"].to_numpy()[f]))) ** 2)) < 0.02


def test_steering_fit(segment: comma2k19.Segment, converted: comma2k19.Converted,
                      log: pd.DataFrame) -> None:
    s = converted.steering
    assert "steering" in converted.fitted
    # the effective ratio of the kinematic bicycle: the RAV4's own (15-17) and its understeer
    assert 10.0 < s.ratio < 40.0 and abs(s.offset_deg) < 2.0
    k = round(1.0 / DT)
    bicycle = _over((log["V"] * np.tan(log["delta"]) / Vehicle().wheelbase).to_numpy(), k)
    gyro = _over(log["r_m"].to_numpy(), k)
    assert np.corrcoef(bicycle, gyro)[0, 1] > 0.8  # left positive, as the gyro
    assert 0.7 < np.polyfit(gyro, bicycle, 1)[0] < 1.3
    given = comma2k19.to_log(segment, steering=comma2k19.Steering(15.0, 0.0),
                             latency=converted.latency)
    assert given.fitted == () and given.steering == comma2k19.Steering(15.0, 0.0)
    wheel = log["delta"] * s.ratio + np.radians(s.offset_deg)  # rad at the steering wheel
    assert np.allclose(given.log["delta"] * 15.0, wheel, atol=1e-12)
    with pytest.raises(LboError, match="steering must be a ratio > 0"):
        comma2k19.Steering(0.0)


def test_log_passes_the_checks(log: pd.DataFrame) -> None:
    assert check_log(log, "comma2k19 example") is True  # with truth
    check_steering(log, Vehicle(), "comma2k19 example")
    check_period(log["t"].to_numpy(), DT, "comma2k19 example")


def _write_layout(folder: Path, rename: dict[str, str] | None = None) -> None:
    """The shipped arrays as a downloaded segment's folder: numpy files without extension."""
    source = resources.files("lbo.sim").joinpath("data", "comma2k19", comma2k19.EXAMPLE)
    with resources.as_file(source) as path, np.load(path) as z:
        for key in z.files:
            file = folder / (rename or {}).get(key, key)
            file.parent.mkdir(parents=True, exist_ok=True)
            with open(file, "wb") as out:  # np.save(path) would add ".npy"
                np.save(out, z[key])


def test_read_original_layout_equals_example(tmp_path: Path,
                                             segment: comma2k19.Segment) -> None:
    _write_layout(tmp_path)
    assert not list(tmp_path.rglob("*.npy"))
    read = comma2k19.read(tmp_path)
    for f in fields(comma2k19.Segment):
        a, b = getattr(read, f.name), getattr(segment, f.name)
        assert a.shape == b.shape and np.array_equal(a, b), f.name


def test_read_takes_car_speed(tmp_path: Path, segment: comma2k19.Segment) -> None:
    can = "processed_log/CAN/"
    _write_layout(tmp_path, {f"{can}speed/t": f"{can}car_speed/t",
                             f"{can}speed/value": f"{can}car_speed/value"})
    assert np.array_equal(comma2k19.read(tmp_path).speed, segment.speed)


def test_missing_file_or_folder_is_one_line(tmp_path: Path) -> None:
    _write_layout(tmp_path)
    (tmp_path / "processed_log/IMU/gyro/value").unlink()
    with pytest.raises(LboError) as e:
        comma2k19.read(tmp_path)
    assert "processed_log/IMU/gyro/value" in str(e.value) and "\n" not in str(e.value)
    assert "global_pose/" in str(e.value)  # what a segment holds
    with pytest.raises(LboError, match="is not a folder") as e:
        comma2k19.read(tmp_path / "nowhere")
    assert "nowhere" in str(e.value) and "\n" not in str(e.value)


def test_wrong_shape_is_one_line(tmp_path: Path) -> None:
    _write_layout(tmp_path)
    with open(tmp_path / "global_pose/frame_orientations", "wb") as out:
        np.save(out, np.zeros((1200, 3)))
    with pytest.raises(LboError, match=r"frame_orientations is float64 \(1200, 3\); expected "
                                       r"numbers \(N, 4\)"):
        comma2k19.read(tmp_path)
