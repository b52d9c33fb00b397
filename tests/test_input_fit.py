"""The kinematic EKF's dead-reckoning terms learned from a log's fixes (lbo.learn.input_fit):
what they undo, their refusals, each recovered on a simulated log whose sensors' errors are
known, and lbo.observe adapt=true filtering with them through outages."""

import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from helpers import observed
from lbo.core.errors import LboError
from lbo.core.paths import CONF_DIR
from lbo.filters.inputs import InputTerms
from lbo.learn import input_fit
from lbo.sim.noise import Noise
from lbo.sim.truth import Sensors
from lbo.sim.vehicle import Vehicle
from lbo.simulate import simulate

SENSORS = ["sensors.speed_scale=0.02", "sensors.steering_offset=0.01"]
"""A speed sensor that reads 2% high and a steering offset of 10 mrad."""


def _log(seed: int = 0, duration: float = 60.0):
    """A single-antenna free drive (fixes at 1 Hz, no heading) whose sensors err as SENSORS,
    its vehicle and noise."""
    with initialize_config_dir(str(CONF_DIR), version_base=None):
        cfg = compose("simulate", ["receiver=single_antenna", "manoeuvre=free_drive",
                                   f"seed={seed}", f"duration={duration}", *SENSORS])
    return simulate(cfg), Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)


def test_the_terms_undo_what_a_simulated_cars_sensors_did():
    sensors = Sensors(steering_offset=0.01, speed_scale=0.02)
    u = np.random.default_rng(0).uniform([0, -0.3], [30, 0.3], (50, 2))
    np.testing.assert_allclose(InputTerms.told(sensors).undo(sensors.logged_inputs(u)), u,
                               rtol=0, atol=1e-12)
    np.testing.assert_array_equal(InputTerms().undo(u), u)  # the defaults undo nothing
    ratio = InputTerms(steering_offset=0.01, steering_factor=1.1).undo(np.array([10.0, 0.11]))
    np.testing.assert_allclose(ratio, [10.0, 1.1 * 0.1], rtol=1e-12)


@pytest.mark.parametrize(("make", "line"), [
    (lambda: InputTerms(speed_factor=3.0), r"^speed_factor must be a number in \[0.5, 2\], got 3"),
    (lambda: InputTerms(steering_offset=0.5), r"^steering_offset must be a number in \[-0.2, "),
    (lambda: input_fit.fit(np.zeros((5, 3)), np.zeros((5, 2)), Vehicle(), Noise.preset("paper"),
                           free=("speed",)), r"^free: unknown term 'speed'; expected some of "),
    (lambda: input_fit.fit(np.full((5, 3), np.nan), np.zeros((5, 2)), Vehicle(),
                           Noise.preset("paper")), r"fewer than two$"),
])
def test_bad_terms_and_a_log_without_fixes_are_one_line(make, line):
    with pytest.raises(LboError, match=line):
        make()


def test_from_the_fixes_alone_it_finds_the_speed_factor_and_the_steering_offset_and_ratio():
    """60 s of a free drive with 1 Hz fixes; its logged steering read through a ratio of 1.1
    as well: the fit lands within 0.3% of the speed factor that undoes the 2% (0.9804), 0.3
    mrad of the offset (9.09 mrad after the ratio) and 0.5% of the ratio (measured: 0.9821,
    9.10 mrad, 1.0995), and its prediction error is below the one with the true terms. Only
    the fixes and the inputs are read: the truth columns are dropped first."""
    log, vehicle, noise = _log()
    m = log[["x_m", "y_m", "psi_m"]].to_numpy()
    u = log[["V", "delta"]].to_numpy() / [1.0, 1.1]
    fitted = input_fit.fit(m, u, vehicle, noise)
    terms = fitted.terms
    assert terms.speed_factor == pytest.approx(1 / 1.02, abs=0.003)
    assert terms.steering_offset == pytest.approx(0.01 / 1.1, abs=3e-4)
    assert terms.steering_factor == pytest.approx(1.1, rel=0.005)
    told = InputTerms(1 / 1.02, 0.01 / 1.1, 1.1)
    assert fitted.loss <= input_fit.loss(m, u, vehicle, noise, told) < 0.5 * fitted.start_loss
    held = input_fit.fit(m, u, vehicle, noise, start=InputTerms(steering_factor=1.1),
                         free=("speed_factor",))
    assert held.terms.steering_factor == 1.1 and held.terms.steering_offset == 0.0


def test_several_logs_are_fitted_together_as_one_prediction_error():
    """Logs of different lengths run as one batch (the shorter padded with rows that hold
    nothing): their prediction errors are each log's own, pooled, and no padded row adds one."""
    (one, vehicle, noise), (two, _, _) = _log(seed=0, duration=20), _log(seed=1, duration=30)
    logs = [(d[["x_m", "y_m", "psi_m"]].to_numpy(), d[["V", "delta"]].to_numpy())
            for d in (one, two)]
    terms = InputTerms(speed_factor=0.99, steering_offset=0.005)
    alone = [input_fit.innovations(m, u, vehicle, noise, terms) for m, u in logs]
    both = input_fit.innovations([m for m, _ in logs], [u for _, u in logs], vehicle, noise,
                                 terms)
    assert len(both) == sum(len(a) for a in alone) > 20
    np.testing.assert_allclose(np.sort(both, axis=0), np.sort(np.concatenate(alone), axis=0),
                               rtol=1e-12, atol=1e-12)
    pooled = input_fit.loss([m for m, _ in logs], [u for _, u in logs], vehicle, noise, terms)
    assert pooled == pytest.approx(np.mean(np.concatenate(alone) ** 2), rel=1e-12)


def test_observe_adapt_fits_the_terms_and_ends_the_outages_closer(tmp_path, capsys):
    """``lbo.observe observer=ekf adapt=true`` on a blanked log (10 s outages): the terms it
    fits from the fixes around the outages are near the truth, and the EKF that filters with
    them ends its outages closer than the EKF on the logged inputs (measured: 6.99 m against
    15.43 m)."""
    log, _, _ = _log(seed=1)
    log.to_csv(tmp_path / "log.csv", index=False)
    common = ["outages.length_s=10", "outages.every_s=25", "vehicle.delta_max=0.6"]  # + offset
    adapted = observed(tmp_path / "log.csv", tmp_path / "adapted.csv", "adapt=true", *common)
    plain = observed(tmp_path / "log.csv", tmp_path / "plain.csv", *common)
    out = capsys.readouterr().out
    assert "adapting: the inputs' terms" in out and "adapted: speed x" in out, out
    # measured: 0.985 (the truth 0.980), from 40 s of fixes around two outages
    assert adapted["input_terms"]["speed_factor"] == pytest.approx(1 / 1.02, abs=0.01)
    assert "input_terms" not in plain
    end = {name: r["outages"].set_index("estimator").loc["ekf", "end_m"]
           for name, r in (("adapted", adapted), ("plain", plain))}
    assert end["adapted"] < 0.7 * end["plain"], end


def test_an_observer_reads_the_inputs_its_terms_undo_and_checks_them_as_logged():
    """``Observer(inputs=...)`` (or set later, as lbo.observe sets the fitted terms): run and
    step give the numbers of the same observer given the undone inputs, for the EKF and for a
    learned window filter; a sample is checked as logged."""
    from lbo.models.net import WindowNet
    from lbo.serve.observer import Observer

    rng = np.random.default_rng(3)
    t = 120
    psi = np.cumsum(np.full(t, 0.004))
    m = np.column_stack([np.cumsum(0.2 * np.cos(psi)), np.cumsum(0.2 * np.sin(psi)), psi])
    m += rng.normal(size=(t, 3)) * [0.5, 0.5, 0.01]
    u = np.column_stack([np.full(t, 10.0), np.full(t, 0.04)])
    terms = InputTerms(speed_factor=0.98, steering_offset=0.01, steering_factor=1.05)
    net = WindowNet("filternet", 20, features="frame")
    for make in (lambda: Observer.load("ekf"), lambda: Observer.from_net(net, form="recursive")):
        told, given = make(), make()
        told.inputs = terms
        ref = given.run(m, terms.undo(u))
        got = told.run(m, u)
        np.testing.assert_array_equal(got.state, ref.state)
        np.testing.assert_array_equal(got.cov, ref.cov)
        steps = np.array([told.step(mk, uk).state for mk, uk in zip(m, u)])
        np.testing.assert_allclose(steps, ref.state, rtol=0, atol=1e-9)
    told = Observer.load("ekf", inputs=InputTerms(steering_offset=0.05))
    with pytest.raises(LboError, match=r"^step 0: .*delta=0\.52"):  # 0.47 rad once undone
        told.step(m[0], [10.0, 0.52])


@pytest.mark.slow  # the robust observer trained at smoke scale, shared by the run
def test_observe_adapt_gives_a_learned_observer_the_terms_it_fits(robust_smoke, manoeuvre,
                                                                  tmp_path):
    """``lbo.observe adapt=true`` with a learned observer (the robust one): the terms are fitted
    by the kinematic EKF on the log's fixes, and the observer reads the inputs they undo: its
    output is ``Observer.load(..., inputs=terms).run``'s."""
    from lbo.filters.inputs import InputTerms
    from lbo.serve.observer import Observer
    from lbo.sim.columns import LOG

    manoeuvre[list(LOG)].to_csv(tmp_path / "log.csv", index=False)
    ckpt = robust_smoke["out"]["checkpoint"]
    result = observed(tmp_path / "log.csv", tmp_path / "est.csv", "adapt=true", observer=ckpt)
    terms = InputTerms(**result["input_terms"])
    assert terms != InputTerms()  # fitted, not the start
    m = manoeuvre[["x_m", "y_m", "psi_m"]].to_numpy()
    u = manoeuvre[["V", "delta"]].to_numpy()
    ref = Observer.load(ckpt, inputs=terms).run(m, u)
    out = pd.read_csv(tmp_path / "est.csv")
    np.testing.assert_allclose(out[["x", "y", "psi"]].to_numpy()[ref.valid], ref.state[ref.valid],
                               rtol=0, atol=1e-9)


def test_a_learned_correction_says_the_input_terms_it_applies():
    """``implied_inputs``: a window filter's learned correction of the kinematic bicycle read
    as input terms. A correction that applies a known speed factor and steering offset
    (written into the correction's place, in its output units) is read back as them; the
    kinematic bicycle, and the zero-initialised correction, imply none; standstill rows are
    not read."""
    import torch
    from torch import nn

    from lbo.models.filternet import WindowFilter

    factor, offset, wheelbase = 0.98, 0.01, 2.7

    class Known(nn.Module):  # reads [0.1 V, 10 delta, 2 r_kin, 2 r_before]; returns d
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            v, delta = 10 * x[:, 0], x[:, 1] / 10
            rate = factor * v * torch.tan(delta - offset) / wheelbase
            r_kin = v * torch.tan(delta) / wheelbase
            return torch.stack([(rate - r_kin) / 0.2, torch.zeros_like(v),
                                torch.full_like(v, (factor - 1) / 0.05)], -1)

    rng = np.random.default_rng(0)
    u = np.column_stack([rng.uniform(0, 25, 500), rng.uniform(-0.3, 0.3, 500)])
    assert WindowFilter(20).implied_inputs(u) == InputTerms()
    net = WindowFilter(20, residual=8).double()
    assert net.implied_inputs(u) == InputTerms()  # zero-initialised: the kinematic bicycle
    net.process = Known()
    implied = net.implied_inputs(u)
    assert implied.speed_factor == pytest.approx(factor, abs=1e-12)
    assert implied.steering_offset == pytest.approx(offset, rel=5e-3)  # to first order
    assert implied.steering_factor == 1.0
    assert net.implied_inputs(np.column_stack([np.zeros(5), np.zeros(5)])) == InputTerms()


def test_a_window_filter_learns_the_input_terms_its_sensors_need():
    """``model.input_terms``: the window filter's process model dead-reckons 4 s stretches of a
    simulated drive of 120 s (speed 2% high, steering 10 mrad off) from the truth; its three
    terms, trained alone by gradient on the positions it reaches, land within 0.3% of the
    speed factor that undoes the 2% and 0.5 mrad of the offset (``learned_inputs``; measured:
    0.9788 for 0.9804, 10.29 mrad, the steering factor 1.016 free beside them), and the
    checkpoint holds them (``input_term_values``). Without the setting there is no such key,
    the terms undo nothing, and a bad value is refused in one line."""
    import torch

    from lbo.models.filternet import WindowFilter

    log, vehicle, _ = _log(duration=120)
    truth = torch.as_tensor(log[["x", "y", "psi"]].to_numpy())
    u = torch.as_tensor(log[["V", "delta"]].to_numpy())
    steps = 200
    starts = torch.arange(0, len(log) - steps - 1, steps // 2)  # (B,) overlapping stretches
    rows = starts[:, None] + torch.arange(steps + 1)  # (B, K + 1)
    net = WindowFilter(20, dt=vehicle.dt, wheelbase=vehicle.wheelbase,
                       input_terms=True).double()
    opt = torch.optim.LBFGS([net.input_term_values], max_iter=30,
                            line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        z, body, loss = truth[starts], torch.zeros(len(starts), 2, dtype=torch.float64), 0.0
        for k in range(steps):  # the filter's prediction through an outage, a step at a time
            v, delta = u[rows[:, k]].T
            z, _, _, body = net.predict_pose(z, v, delta, body)
            loss = loss + ((z[:, :2] - truth[rows[:, k + 1], :2]) ** 2).sum(-1).mean()
        loss = loss / steps
        loss.backward()
        return loss

    opt.step(closure)
    learned = net.learned_inputs()
    assert learned.speed_factor == pytest.approx(1 / 1.02, abs=0.003)
    assert learned.steering_offset == pytest.approx(0.01, abs=5e-4)
    assert "input_term_values" in net.state_dict()
    assert net.implied_inputs(u.numpy()) == learned  # no correction: the terms themselves
    plain = WindowFilter(20)
    assert "input_term_values" not in plain.state_dict()
    assert plain.learned_inputs() == InputTerms()
    with pytest.raises(LboError, match=r"^model.input_terms: expected true or false, got 1$"):
        WindowFilter(20, input_terms=1)
