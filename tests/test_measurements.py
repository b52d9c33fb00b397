"""What the sensors told, by name (:class:`lbo.Measurements`): built once from a log or
arrays, read by field everywhere after, and taken by :class:`lbo.Observer` in place of the
positional ``m`` and ``receiver``."""

import numpy as np
import pytest

from lbo import LboError, Measurements, Observer
from lbo.filters import measure
from lbo.sim import gyro_drive
from lbo.sim.columns import MEAS, RECEIVER, WINDOW


@pytest.fixture(scope="module")
def log():
    return gyro_drive.draw(0).iloc[:400].reset_index(drop=True)


def test_each_column_lands_in_its_named_field_and_back(log):
    meas = Measurements.from_frame(log)
    np.testing.assert_array_equal(meas.fix, log[["x_m", "y_m"]].to_numpy())
    np.testing.assert_array_equal(meas.heading, log["psi_m"].to_numpy())
    np.testing.assert_array_equal(meas.fix_sigma, log[["sx_m", "sy_m"]].to_numpy())
    np.testing.assert_array_equal(meas.velocity, log[["ve_m", "vn_m"]].to_numpy())
    np.testing.assert_array_equal(meas.velocity_sigma, log["sv_m"].to_numpy())
    np.testing.assert_array_equal(meas.gyro, log["r_m"].to_numpy())
    np.testing.assert_array_equal(meas.pose, log[list(MEAS)].to_numpy())
    np.testing.assert_array_equal(meas.receiver, log[list(RECEIVER)].to_numpy())
    np.testing.assert_array_equal(meas.has_fix, log[["x_m", "y_m"]].notna().all(axis=1))
    assert meas.has_gyro.all() and not meas.has_heading.any() and meas.has_velocity.any()
    one = meas[7]
    assert one.fix.shape == (2,) and one.gyro == log["r_m"][7]
    assert len(meas) == len(log) and len(meas[10:20]) == 10


def test_a_log_without_receiver_columns_holds_none():
    import pandas as pd

    frame = pd.DataFrame({"x_m": [0.0, np.nan], "y_m": [1.0, np.nan], "psi_m": [0.1, np.nan]})
    meas = Measurements.from_frame(frame)
    assert not meas.reads_receiver and list(meas.has_fix) == [True, False]
    with pytest.raises(LboError, match=r"^measurements: the log has no column psi_m "):
        Measurements.from_frame(frame.drop(columns="psi_m"))


@pytest.mark.parametrize("m, receiver", [(np.zeros((5, 2)), None),
                                         (np.zeros((5, 3)), np.zeros((4, 7))),
                                         (np.zeros((5, 3)), np.zeros((5, 6)))])
def test_a_wrong_shape_is_one_line(m, receiver):
    with pytest.raises(LboError, match=r"^measurements: expected m \(\.\.\., 3\) \[x_m, y_m, "
                                       r"psi_m\] and receiver \(\.\.\., 7\)"):
        Measurements.of(m, receiver)


def test_the_filters_rows_are_its_fields_with_the_velocitys_course(log):
    meas = Measurements.from_frame(log)
    V = log["V"].to_numpy()
    rows = measure.rows(meas, V)
    assert rows.shape == (len(log), len(measure.CHANNELS))
    np.testing.assert_array_equal(rows[:, :3], meas.pose)
    np.testing.assert_array_equal(rows[:, 3:6], log[["sx_m", "sy_m", "spsi_m"]].to_numpy())
    course, s_course = measure.course_over_ground(meas.velocity[:, 0], meas.velocity[:, 1],
                                                  meas.velocity_sigma, V)
    np.testing.assert_array_equal(rows[:, 6], course)
    np.testing.assert_array_equal(rows[:, 7], s_course)
    # any leading shape: a batch of logs at once
    both = measure.rows(Measurements.of(np.stack([meas.pose] * 2),
                                        np.stack([meas.receiver] * 2)), np.stack([V, V]))
    np.testing.assert_array_equal(both[1], rows)


@pytest.mark.parametrize("name", ["gyro", "ekf"])
def test_the_observer_takes_them_in_place_of_m_and_receiver(log, name):
    m, u = log[list(MEAS)].to_numpy(), log[["V", "delta"]].to_numpy()
    r = log[list(RECEIVER)].to_numpy()
    meas = Measurements.from_frame(log)
    obs = Observer.load(name)
    arrays, typed = obs.run(m, u, receiver=r), obs.run(meas, u)
    np.testing.assert_array_equal(typed.state, arrays.state)
    np.testing.assert_array_equal(typed.valid, arrays.valid)
    stepped = []
    obs.reset()
    for k in range(60):
        stepped.append(obs.step(meas[k], u[k]).state)
    obs.reset()
    for k in range(60):
        np.testing.assert_array_equal(obs.step(m[k], u[k], r[k]).state, stepped[k])
    with pytest.raises(LboError, match=r"^run: the receiver's channels belong in the "
                                       "Measurements given, not beside them$"):
        obs.run(meas, u, receiver=r)


def test_the_readmes_python_block_runs_as_printed_and_its_two_forms_agree(monkeypatch):
    """The README's "From Python" block, run as printed from the repository's root: the
    whole log and the control loop give the same estimates."""
    import re

    from lbo.core.paths import REPO_ROOT

    text = (REPO_ROOT / "README.md").read_text().split("## From Python", 1)[1]
    block = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    monkeypatch.chdir(REPO_ROOT)
    scope: dict = {}
    exec(compile(block, "README.md", "exec"), scope)  # lbo's own README, not a user's file
    assert scope["est"].shape == (len(scope["u"]), 3) and scope["valid"].all()
    np.testing.assert_allclose((scope["x"], scope["y"], scope["psi"]), scope["est"][-1],
                               atol=1e-9)


def test_the_torch_twin_names_each_column_of_a_row_and_of_a_receiver_window():
    """Each field of :func:`lbo.filters.measure.row_channels` (of a NumPy row and a torch
    one) and :func:`lbo.models.channels.feature_channels` is the column of its name (a row
    whose every column holds its own index)."""
    import torch

    from lbo.filters.measure import row_channels
    from lbo.models.channels import feature_channels
    from lbo.models.receiver_window import FEATURES

    at = {n: float(i) for i, n in enumerate(measure.CHANNELS)}
    for row in (torch.arange(len(at), dtype=torch.float64), np.arange(len(at), dtype=float)):
        c = row_channels(row)
        assert c.pose.tolist() == [at["x_m"], at["y_m"], at["psi_m"]]
        assert c.fix.tolist() == [at["x_m"], at["y_m"]] and float(c.heading) == at["psi_m"]
        assert c.sigma.tolist() == [at["sx_m"], at["sy_m"], at["spsi_m"]]
        assert (float(c.course), float(c.course_sigma)) == (at["course"], at["s_course"])
    f = feature_channels(torch.arange(len(FEATURES), dtype=torch.float64))
    at = {n: float(i) for i, n in enumerate(FEATURES)}
    named = {"heading": "dpsi", "course": "dcourse", "course_sigma": "s_course",
             "has_fix": "fix", "has_heading": "heading", "has_course": "course_held",
             "V": "V", "delta": "delta", "gyro": "r_m", "has_gyro": "gyro"}
    for field, column in named.items():
        assert float(getattr(f, field)) == at[column], field
    assert f.pose.tolist() == [at["dx"], at["dy"], at["dpsi"]] and f.fix.tolist() == [0.0, 1.0]
    assert f.sigma.tolist() == [at["sx"], at["sy"], at["spsi"]]


def test_the_torch_twin_names_each_column_of_a_paper_window():
    """:func:`lbo.models.channels.window_channels`: a paper window's columns by name (a window
    whose every column holds its own index), ``fix`` the sixth where there is one and 1 at
    every row of a window of five."""
    import torch

    from lbo.models.channels import window_channels

    at = {n: float(i) for i, n in enumerate((*WINDOW, "fix"))}
    w = window_channels(torch.arange(6, dtype=torch.float64))
    assert w.pose.tolist() == [at["x_m"], at["y_m"], at["psi_m"]]
    assert w.inputs.tolist() == [at["V"], at["delta"]]
    assert (float(w.V), float(w.delta), float(w.fix)) == (at["V"], at["delta"], at["fix"])
    five = window_channels(torch.arange(10, dtype=torch.float64).view(2, 5))
    assert five.fix.tolist() == [1.0, 1.0] and five.V.tolist() == [3.0, 8.0]
