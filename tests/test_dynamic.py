"""The car that slips (lbo.sim.dynamic), the sensors' errors (lbo.sim.truth) and the data sets drawn
from them: closed forms of steady-state cornering, the kinematic limit, the integrator's error,
the Gauss-Markov drift, and the paper's sets left byte for byte as they were."""


import numpy as np
import pandas as pd
import pytest
import torch

from helpers import compose_cfg
from lbo.core.errors import LboError
from lbo.learn.draws import gauss_markov as gauss_markov_torch
from lbo.sim import dynamic
from lbo.sim.datasets import MAKERS, build, spec_from_cfg
from lbo.sim.dynamic import SingleTrack, derivatives, rear_slip, steady_state, step, tyre_force
from lbo.sim.truth import Sensors, Truth, config_dict, from_cfg, from_dict, gauss_markov
from lbo.sim.vehicle import f as kinematic_f

CAR = SingleTrack()
DT = 0.02


def _settle(v: float, delta: float, seconds: float = 6.0) -> np.ndarray:
    """The car's state after ``seconds`` at constant speed and steering, from straight."""
    s = np.zeros((1, 5))
    u = np.array([[v, delta]])
    for _ in range(int(seconds / DT)):
        s = step(s, u, DT, CAR)
    return s[0]


def test_default_car_is_a_plausible_understeering_passenger_car():
    assert CAR.wheelbase == pytest.approx(2.7)
    # K = (m / L)(l_r / C_f - l_f / C_r) = (1500 / 2.7)(1.5 / 8e4 - 1.2 / 1e5)
    assert CAR.understeer_gradient == pytest.approx(1500 / 2.7 * (1.5 / 8e4 - 1.2 / 1e5))
    assert 1 < np.degrees(CAR.understeer_gradient * 9.81) < 4  # degrees per g of a road car
    fzf, fzr = CAR.axle_loads
    assert fzf + fzr == pytest.approx(1500 * 9.81) and fzf > fzr


@pytest.mark.parametrize("v", [8.0, 15.0, 25.0])
def test_steady_state_yaw_rate_follows_the_understeer_gradient(v):
    a_y = 1.0  # m/s^2: small slip, where the tyres are linear
    delta = a_y * (CAR.wheelbase + CAR.understeer_gradient * v**2) / v**2
    s = _settle(v, delta)
    r_closed = v * delta / (CAR.wheelbase + CAR.understeer_gradient * v**2)
    assert s[4] == pytest.approx(r_closed, rel=5e-3)
    assert v * s[4] == pytest.approx(a_y, rel=5e-3)
    # understeer: the car turns less than the kinematic bicycle at the same steering
    assert s[4] < v * np.tan(delta) / CAR.wheelbase * (1 - 0.5 * CAR.understeer_gradient
                                                        * v**2 / CAR.wheelbase)


@pytest.mark.parametrize("a_y", [1.0, 2.0])
def test_rear_axle_slips_at_the_closed_form_angle(a_y):
    v = 15.0
    delta = a_y * (CAR.wheelbase + CAR.understeer_gradient * v**2) / v**2
    s = _settle(v, delta)
    closed = CAR.mass * a_y * CAR.l_f / (CAR.wheelbase * CAR.c_r)  # a_r = F_yr / C_r
    slip = rear_slip(s, np.array([v, delta]), CAR)
    assert -slip == pytest.approx(closed, rel=2e-2)  # the rear axle moves to the outside
    v_y, r = steady_state(v, delta, CAR)
    assert s[3] == pytest.approx(v_y, abs=5e-3) and s[4] == pytest.approx(r, rel=1e-2)


def test_tyres_saturate_at_mu_times_the_load():
    fzf, _ = CAR.axle_loads
    assert tyre_force(np.array(1.0), CAR.c_f, CAR.mu * fzf) == pytest.approx(CAR.mu * fzf,
                                                                             rel=1e-6)
    assert tyre_force(np.array(1e-4), CAR.c_f, fzf) == pytest.approx(CAR.c_f * 1e-4, rel=1e-6)
    s = _settle(15.0, 0.3)  # steering for 2.5 g on the kinematic bicycle
    assert 15.0 * s[4] <= 1.02 * CAR.mu * dynamic.G


def test_below_a_few_metres_per_second_it_is_the_kinematic_bicycle():
    rng = np.random.default_rng(0)
    s = np.column_stack([rng.normal(size=(50, 3)), rng.normal(0, 0.5, (50, 2))])
    u = np.column_stack([rng.uniform(0, CAR.v_kinematic, 50), rng.uniform(-0.5, 0.5, 50)])
    np.testing.assert_allclose(derivatives(s, u, CAR)[:, :3], kinematic_f(s[:, :3], u, 2.7),
                               atol=1e-12)
    assert np.all(rear_slip(s, u, CAR) == 0)
    # and just above, the dynamic model's yaw rate approaches the kinematic one
    v = 2.5
    r = steady_state(v, 0.1, CAR)[1]
    assert r == pytest.approx(v * 0.1 / 2.7, rel=CAR.understeer_gradient * v**2 / 2.7 + 1e-9)


def test_rk4_sub_steps_integrate_accurately():
    t = np.arange(100) * DT
    u = np.stack([np.full(100, 12.0), 0.08 * np.sin(2 * np.pi * 0.5 * t)], -1)[None]
    z0 = np.zeros((1, 3))

    def run(substeps: int) -> np.ndarray:
        car = SingleTrack(substeps=substeps)
        return dynamic.simulate(z0, u, DT, car)[0]

    ref = run(64)
    errors = [np.abs(run(n) - ref)[:, :3].max() for n in (2, 4)]
    assert errors[1] < 1e-6  # the default: micrometres over 2 s of slalom
    assert errors[0] / errors[1] > 10  # fourth order: halving the step gains about 16


def test_gauss_markov_drift_has_its_variance_and_correlation_time():
    rng = np.random.default_rng(0)
    tau, sigma = 1.0, 0.5
    b = gauss_markov((400, 1500), DT, tau, sigma, rng)
    lag = int(tau / DT)
    assert b[:, 0].var() == pytest.approx(sigma**2, rel=0.2)  # stationary from the start
    assert b.var() == pytest.approx(sigma**2, rel=0.05)
    corr = (b[:, lag:] * b[:, :-lag]).mean() / b.var()
    assert corr == pytest.approx(np.exp(-1), abs=0.03)
    # the training draws' version: the same process, a window at a time
    g = torch.Generator().manual_seed(0)
    bt = gauss_markov_torch((2000, 200), tau / DT, g).numpy()
    assert bt.var() == pytest.approx(1.0, rel=0.05)
    assert bt[:, 0].var() == pytest.approx(1.0, rel=0.1)
    corr_t = (bt[:, lag:] * bt[:, :-lag]).mean() / bt.var()
    assert corr_t == pytest.approx(np.exp(-1), abs=0.03)


@pytest.mark.parametrize("car, sensors, field", [
    ({"name": "bicycle"}, {}, "car.name"),
    ({"name": "dynamic", "l_f": 1.0}, {}, "car.l_f + car.l_r"),
    ({"name": "dynamic", "mass": -1.0}, {}, "car.mass"),
    ({"name": "dynamic", "wheels": 4}, {}, "car.wheels"),
    ({"name": "kinematic", "mass": 1500.0}, {}, "car.mass"),
    ({"name": "kinematic", "gnss_sigma": 0.5}, {}, "car.gnss_sigma"),  # a sensor's, not the car's
    ({"name": "kinematic"}, {"gnss_sigma": -0.1}, "sensors.gnss_sigma"),
    ({"name": "kinematic"}, {"gnss_tau": 0.0}, "sensors.gnss_tau"),
    ({"name": "kinematic"}, {"mu": 0.8}, "sensors.mu"),  # the car's, not a sensor's
    ({"name": "dynamic", "substeps": 0}, {}, "car.substeps"),
    ({"name": "dynamic", "process_scale": -0.1}, {}, "car.process_scale"),
    ({"name": "kinematic", "process_scale": "a lot"}, {}, "car.process_scale"),
    ({"name": "kinematic", "lateral_sigma": [0.01, 0.0]}, {}, "car.lateral_sigma"),
    ({"name": "dynamic", "lateral_sigma": 0.01}, {}, "car.lateral_sigma"),
    ({"name": "dynamic", "lateral_sigma": [0.01, -0.1]}, {}, "car.lateral_sigma"),
])
def test_bad_car_or_sensors_names_the_field(car, sensors, field):
    with pytest.raises(LboError, match=field.replace("+", r"\+")) as e:
        from_cfg(car, sensors, 2.7)
    assert "\n" not in str(e.value)


def test_a_truth_kept_as_one_mapping_reads_back_split():
    """A data set's manifest and a checkpoint keep the truth as one mapping (the car's keys,
    then the sensors'): it reads back as the car and sensors it was drawn from."""
    cfg = compose_cfg("datagen", ["data=dynamic_drift"])
    truth = from_cfg(cfg.car, cfg.sensors, 2.7)
    assert truth.sensors.gnss_sigma == 0.5 and truth.car is not None
    assert from_dict(truth.to_dict(), 2.7) == truth
    assert from_dict(config_dict(cfg), 2.7) == truth
    assert list(config_dict(cfg))[:2] == ["name", "mass"] and from_dict(None, 2.7) == Truth()


def _fingerprint(df: pd.DataFrame) -> tuple[float, float]:
    """Two sums over every value of a set: of |v|, and of v weighted by its row and column.

    Not a hash of the bytes: numpy's SIMD sin, cos and tan differ in the last bit between CPUs
    (AVX-512 or AVX2 kernels), so the same generator writes sets a few 1e-16 apart on two
    machines. Any real change (another draw, another step, rows or columns moved) moves these
    sums by far more than the 1e-10 relative the test allows."""
    v = df.to_numpy(float)
    i, j = np.indices(v.shape)
    return float(np.abs(v).sum()), float((v * np.cos(0.1 * i + 0.7 * j)).sum())


def test_kinematic_truth_leaves_the_paper_sets_byte_for_byte_unchanged(tmp_path):
    # the smoke sets as lbo generated them before truth models existed (commit e260c94); that
    # commit's generator and today's give byte-identical sets on one machine (checked on the
    # machine these numbers were taken on); _fingerprint says why they are sums, not a hash
    spec = spec_from_cfg(compose_cfg("datagen", ["data=smoke", f"data.root={tmp_path}"]))
    assert spec.truth == Truth() and spec.digest == "a8c688af2968"
    expected = {"train": (3231567.7921262095, -33097.404685739486),
                "val": (829515.9839430884, -2382.063637456651),
                "test": (5356256.759464549, -7263.101887886825)}
    for name, make in MAKERS.items():
        size, weighted = _fingerprint(make(spec))
        assert size == pytest.approx(expected[name][0], rel=1e-10), name
        assert weighted == pytest.approx(expected[name][1], abs=1e-10 * size), name
    # one machine, one seed: the same bytes every time
    assert spec_from_cfg(compose_cfg("datagen", ["data=smoke", f"data.root={tmp_path}"])) == spec
    frames = [make(spec) for make in MAKERS.values()]
    again = [make(spec) for make in MAKERS.values()]
    for a, b in zip(frames, again):
        pd.testing.assert_frame_equal(a, b, check_exact=True)


@pytest.fixture(scope="module")
def dynamic_sets(tmp_path_factory):
    root = tmp_path_factory.mktemp("dyn")

    def sets(*overrides: str) -> dict[str, pd.DataFrame]:
        cfg = compose_cfg("datagen", ["data=smoke", "car=dynamic", f"data.root={root}",
                                      "data.train.n_traj=8", *overrides])
        return build(spec_from_cfg(cfg), progress=False)[1]

    return sets


def test_dynamic_sets_keep_the_schema_and_understeer_in_corners(dynamic_sets):
    sets = dynamic_sets()
    for name in ("train", "val", "test"):
        assert list(sets[name].columns[:11]) == ["traj", "k", "t", "x", "y", "psi", "V",
                                                 "delta", "x_m", "y_m", "psi_m"]
    # the true heading turns about a quarter less than the logged steering says, in corners
    # (the controller steers more to hold the path); on the kinematic bicycle it turns as said
    t = sets["test"]
    t = t[t["alpha"] == 0].sort_values(["traj", "k"])
    r = np.diff(np.unwrap(t["psi"].to_numpy())) / DT
    r_kin = (t["V"] * np.tan(t["delta"]) / 2.7).to_numpy()[:-1]
    corner = (t["traj"].to_numpy()[1:] == t["traj"].to_numpy()[:-1]) & (np.abs(r_kin) > 0.2)
    assert corner.sum() > 500
    assert 0.6 < np.sum(r[corner] * np.sign(r_kin[corner])) / np.sum(np.abs(r_kin[corner])) < 0.85


def test_sensor_errors_change_the_logs_not_the_truth(dynamic_sets):
    clean = dynamic_sets()["test"]
    off = dynamic_sets("sensors.steering_offset=0.01", "sensors.speed_scale=0.02",
                       "sensors.gnss_sigma=0.5", "sensors.gnss_tau=5.0")["test"]
    pd.testing.assert_frame_equal(clean[["x", "y", "psi"]], off[["x", "y", "psi"]])
    np.testing.assert_allclose(off["delta"] - clean["delta"], 0.01, atol=1e-12)
    np.testing.assert_allclose(off["V"], 1.02 * clean["V"], rtol=1e-12)
    # the drift: per unit of alpha, the x error's variance is 1 + 0.5^2 and consecutive errors
    # correlate by 0.25 / 1.25 (a 5 s correlation time is 250 steps); white noise: 1 and 0
    for df, var, lag1 in ((clean, 1.0, 0.0), (off, 1.25, 0.2)):
        t = df[df["alpha"] > 0].sort_values(["alpha", "traj", "k"])
        e = ((t["x_m"] - t["x"]) / t["alpha"]).to_numpy()
        same = t["traj"].to_numpy()[1:] == t["traj"].to_numpy()[:-1]
        assert np.mean(e**2) == pytest.approx(var, abs=0.08)
        assert np.sum(e[1:] * e[:-1] * same) / np.sum(e[1:] ** 2 * same) == pytest.approx(
            lag1, abs=0.04)


def test_sensors_are_off_by_default():
    assert Sensors().off and Truth().default
    u = np.array([[10.0, 0.1]])
    assert Sensors().logged_inputs(u) is u


def test_a_car_moves_as_its_dynamics_say_up_to_a_tenth_of_the_papers_random_walk(
        dynamic_sets):
    # car=dynamic carries process_scale 0.1: the pose's unmodelled steps are a tenth of the
    # noise preset's sigmas. Rolled forward one step from each true state with the true car,
    # what is left is that noise.
    truth = from_cfg(compose_cfg("datagen", ["car=dynamic"]).car, None, 2.7)
    assert truth.process_scale == pytest.approx(0.1)
    for scale in (0.1, 1.0):
        train = dynamic_sets(f"car.process_scale={scale}")["train"].sort_values(["traj", "k"])
        z = train[["x", "y", "psi"]].to_numpy().reshape(8, -1, 3)
        u = train[["V", "delta"]].to_numpy().reshape(8, -1, 2)
        # v_y and r are not logged: take them from a noise-free run of the same inputs, which
        # the process noise hardly moves (it acts on the pose only)
        s = dynamic.simulate(z[:, 0], u, DT, CAR)
        s[..., :3] = z
        ahead = step(s[:, :-1], u[:, :-1], DT, CAR)[..., :3]
        w = z[:, 1:] - ahead
        w[..., 2] = (w[..., 2] + np.pi) % (2 * np.pi) - np.pi
        sigma = np.array([0.2, 0.2, 3.4e-3]) / 3 * scale  # the paper preset's, scaled
        np.testing.assert_allclose(w.reshape(-1, 3).std(0), sigma, rtol=0.05)


def test_process_scale_1_keeps_the_dynamic_sets_of_the_papers_random_walk(tmp_path):
    # the field only scales: process_scale=1 is the random walk of the noise preset, and a
    # kinematic truth with process_scale=1 is the paper's setting (default, same digest)
    kin = spec_from_cfg(compose_cfg("datagen", ["data=smoke", "car.process_scale=1.0",
                                                f"data.root={tmp_path}"]))
    assert kin.truth.default and kin.digest == "a8c688af2968"
    assert kin.motion_noise is kin.noise
    half = spec_from_cfg(compose_cfg("datagen", ["data=smoke", "car.process_scale=0.5",
                                                 f"data.root={tmp_path}"]))
    assert not half.truth.default and half.digest != kin.digest
    np.testing.assert_allclose(half.motion_noise.process_sigma,
                               0.5 * np.asarray(kin.noise.process_sigma))
    assert half.motion_noise.measurement_sigma == kin.noise.measurement_sigma


def test_a_car_pushed_about_carries_its_disturbances_in_its_lateral_states_alone(dynamic_sets):
    """``car=gusty`` (``car.lateral_sigma``): white disturbances of v_y and r after each step.
    Rolled one step from each true state of a test set with the true car, what is left on v_y
    and r is that disturbance, and on the pose the process noise alone; the training set moves
    too. A car without them keeps its sets' digest (the field is not in its truth's mapping),
    and the EKF told the car is told them in its process noise."""
    from lbo.filters.dynamic_ekf import Q_LATERAL_SIGMA, DynamicStepper
    from lbo.sim.columns import LATERAL
    from lbo.sim.vehicle import Vehicle

    gusty = from_cfg(compose_cfg("datagen", ["car=gusty"]).car, None, 2.7)
    plain = from_cfg(compose_cfg("datagen", ["car=dynamic"]).car, None, 2.7)
    assert gusty.lateral_sigma == (0.01, 0.002) and from_dict(gusty.to_dict(), 2.7) == gusty
    assert "lateral_sigma" not in plain.to_dict() and plain.lateral_sigma == (0.0, 0.0)
    pushed = dynamic_sets("+car.lateral_sigma=[0.01,0.002]")
    test = pushed["test"]
    t = test[test["alpha"] == 0].sort_values(["traj", "k"])
    s = t[["x", "y", "psi", *LATERAL]].to_numpy()
    u = t[["V", "delta"]].to_numpy()
    same = (t["traj"].to_numpy()[1:] == t["traj"].to_numpy()[:-1]) & (np.diff(t["k"]) == 1)
    w = (s[1:] - step(s[:-1], u[:-1], DT, CAR))[same]
    assert len(w) > 1000
    np.testing.assert_allclose(w[:, 3:].std(0), [0.01, 0.002], rtol=0.05)
    np.testing.assert_allclose(w[:, :2].std(0), 0.2 / 3 * 0.1, rtol=0.05)  # the pose's own
    assert not np.allclose(pushed["train"][["x", "y"]], dynamic_sets()["train"][["x", "y"]])
    m0 = np.zeros((1, 3))
    told = DynamicStepper(m0, Vehicle(), np.eye(3), np.eye(3)[None], car=CAR,
                          lateral_sigma=gusty.lateral_sigma)
    np.testing.assert_allclose([told.Q[0, 3, 3], told.Q[0, 4, 4]],
                               np.square(Q_LATERAL_SIGMA) + np.square([0.01, 0.002]))


def test_no_test_manoeuvre_corners_harder_than_the_cap(dynamic_sets):
    from lbo.sim.datasets import peak_lateral_g

    def peaks(df):
        t = df[df["alpha"] == df["alpha"].min()].sort_values(["traj", "k"])
        n = t.groupby("traj").size().to_numpy()
        arr = {c: [g[c].to_numpy() for _, g in t.groupby("traj")] for c in ("psi", "V")}
        width = n.max()

        def pad(xs):
            return np.stack([np.pad(x, (0, width - len(x)), mode="edge") for x in xs])

        z = np.zeros((len(n), width, 3))
        z[..., 2] = pad(arr["psi"])
        u = np.zeros((len(n), width, 2))
        u[..., 0] = pad(arr["V"])
        return peak_lateral_g(z, u, n, DT), n

    # the weave at the paper's speeds asks for more than the tyres give: capped, it is driven
    # slower (more steps), the others at their speeds (the longer weave changes the shapes of
    # the process-noise draws, so their peaks move by the noise's share only)
    manoeuvres = "data.test.manoeuvres=[weave,hairpin]"
    free, n_free = peaks(dynamic_sets(manoeuvres)["test"])
    capped, n_capped = peaks(dynamic_sets(manoeuvres,
                                          "+data.test.max_lateral_g=0.6")["test"])
    assert free[0] > 0.6 and free[1] < 0.6
    assert capped[0] <= 0.6 and n_capped[0] > n_free[0]
    assert n_capped[1] == n_free[1] and capped[1] == pytest.approx(free[1], rel=0.1)


def test_a_car_that_slips_leaves_its_lateral_states_in_the_scored_sets(dynamic_sets):
    """The validation and test sets of a car that slips hold its true v_y and r (no observer
    reads them: they score a side slip); the heading turns at that r, up to the process
    noise; the kinematic bicycle's sets have no such columns."""
    sets = dynamic_sets()
    assert "v_y" not in sets["train"] and {"v_y", "r"} <= set(sets["val"].columns)
    t = sets["test"]
    t = t[t["alpha"] == 0].sort_values(["traj", "k"])
    same = t["traj"].to_numpy()[1:] == t["traj"].to_numpy()[:-1]
    turned = np.diff(np.unwrap(t["psi"].to_numpy())) / DT
    r = t["r"].to_numpy()
    r_step = 0.5 * (r[1:] + r[:-1])  # the step's mean rate, as the car's integrator takes it
    assert np.corrcoef(turned[same], r_step[same])[0, 1] > 0.99
    beta = np.arctan2(t["v_y"], t["V"])
    assert 0.005 < np.abs(beta).max() < 0.2  # the car slips, within a road car's range


@pytest.mark.slow  # 16 s: two runs of the dynamic EKF over the smoke test set
def test_the_oracle_told_the_car_finds_its_lateral_states_in_the_set(dynamic_sets, tmp_path):
    """oracle_dynamic_lateral reads a test set's padded arrays (the lateral states beside the
    pose, schema.to_arrays) and, told the car, gives its side slip on the scored rows; told
    tyres 3x too soft, it is far off. No truth column is read: the pose fixes and inputs."""
    from dataclasses import replace

    from lbo.filters.classical import oracle_dynamic_lateral
    from lbo.sim import schema

    cfg = compose_cfg("datagen", ["data=smoke", "car=dynamic", f"data.root={tmp_path}",
                                  "data.train.n_traj=8"])
    spec = spec_from_cfg(cfg)
    t = schema.to_arrays(dynamic_sets()["test"])
    t = t.take(t.alpha == 1.0)
    assert t.lateral is not None and t.lateral.shape == (*t.m.shape[:2], 2)
    truth = np.arctan2(t.lateral[..., 0], t.u[..., 0])[t.mask]
    _, lat = oracle_dynamic_lateral(t.m, t.u, spec.vehicle, spec.noise, t.alpha, spec.truth)
    told = np.rad2deg(np.sqrt(np.mean((lat.beta(t.u[..., 0])[t.mask] - truth) ** 2)))
    soft = replace(spec.truth, car=replace(spec.truth.car, c_f=spec.truth.car.c_f / 3,
                                           c_r=spec.truth.car.c_r / 3))
    _, wrong = oracle_dynamic_lateral(t.m, t.u, spec.vehicle, spec.noise, t.alpha, soft)
    off = np.rad2deg(np.sqrt(np.mean((wrong.beta(t.u[..., 0])[t.mask] - truth) ** 2)))
    assert told < 1e-3 and off > 100 * told
    planted = replace(t, lateral=np.zeros_like(t.lateral), z=np.zeros_like(t.z))
    again = oracle_dynamic_lateral(planted.m, planted.u, spec.vehicle, spec.noise,
                                   planted.alpha, spec.truth)[1]
    assert np.array_equal(again.mean, lat.mean)


@pytest.mark.slow  # 8 s: the dynamic EKF over two levels of the smoke test set
def test_the_lateral_states_are_scored_per_level_and_written_by_evaluate(dynamic_sets, tmp_path,
                                                                         capsys):
    """lbo.scoring.lateral: beta, v_y and r of each estimator against the set's own, per noise
    level over the scored rows; the EKF told the car far below the kinematic bicycle's and
    straight ahead's; only the oracle gives beta a variance, and a learned body told its
    error; no truth column is read. lbo.evaluate's part writes it as lateral.csv and prints
    beta in degrees."""
    from dataclasses import replace

    from lbo.evaluate import _lateral
    from lbo.scoring import lateral
    from lbo.sim import schema

    cfg = compose_cfg("datagen", ["data=smoke", "car=dynamic", f"data.root={tmp_path}",
                                  "data.train.n_traj=8"])
    spec = spec_from_cfg(cfg)
    t = schema.to_arrays(dynamic_sets()["test"])
    t = t.take(np.isin(t.alpha, [1.0, 3.0]))
    scores = lateral.table(t, spec.vehicle, spec.noise, spec.truth)
    assert list(scores.columns) == lateral.COLUMNS and len(scores) == 6
    by = scores.set_index(["observer", "alpha"])
    at1 = t.mask & (t.alpha == 1.0)[:, None]
    beta = np.arctan2(t.lateral[..., 0], t.u[..., 0])  # exact inputs: the logged V is the car's
    assert by.loc[("zero", 1.0), "rmse_beta"] == pytest.approx(np.sqrt(np.mean(beta[at1] ** 2)))
    assert by.loc[("zero", 1.0), "rmse_vy"] == pytest.approx(
        np.sqrt(np.mean(t.lateral[..., 0][at1] ** 2)))
    assert np.isnan(by.loc[("zero", 1.0), "rmse_r"])
    for a in (1.0, 3.0):
        told = by.loc[("oracle_dynamic", a)]
        assert told["rmse_beta"] < 0.1 * by.loc[("kinematic", a), "rmse_beta"]
        assert told["rmse_beta"] < 0.1 * by.loc[("zero", a), "rmse_beta"]
        assert np.isfinite(told["nees_beta"]) and np.isnan(by.loc[("kinematic", a), "nees_beta"])
    # the estimates read the fixes and the inputs only
    planted = replace(t, lateral=np.zeros_like(t.lateral), z=np.zeros_like(t.z))
    again = lateral.estimates(planted, spec.vehicle, spec.noise, spec.truth)
    first = lateral.estimates(t, spec.vehicle, spec.noise, spec.truth)
    assert all(np.array_equal(again[n]["beta"], first[n]["beta"]) for n in first)
    path = _lateral(t, spec.vehicle, spec.noise, spec.truth, {}, {}, tmp_path)  # none learned
    pd.testing.assert_frame_equal(pd.read_csv(path), scores)
    # a learned body 0.05 m/s off in v_y at every row, with its error (measured, uncentred:
    # a floor of 0.05^2 and no part that grows with v_y): beta's variance from it makes a
    # NEES of one, to first order in the offset
    off = t.lateral + np.array([0.05, 0.0])
    error = lateral.body_error(off, t)
    np.testing.assert_allclose(error, [[0.05 ** 2, 0.0], [0.0, 0.0]], atol=1e-15)
    mine = lateral.table(t, spec.vehicle, spec.noise, spec.truth, {"body": off},
                         {"body": error}).set_index(["observer", "alpha"])
    assert mine.loc[("body", 1.0), "rmse_vy"] == pytest.approx(0.05)
    assert mine.loc[("body", 1.0), "nees_beta"] == pytest.approx(1.0, rel=0.02)
    assert np.isnan(lateral.table(t, spec.vehicle, spec.noise, spec.truth, {"body": off})
                    .set_index(["observer", "alpha"]).loc[("body", 1.0), "nees_beta"])
    said = capsys.readouterr().out
    assert "beta (deg)" in said and f"lateral states: {path}" in said


def test_a_bodys_lateral_variances_come_from_its_error_and_a_bad_one_is_refused_in_one_line():
    """lbo.serve.estimate.lateral_variance: per state a floor and a part relative to the
    state's size, beta's v_y's through atan2(v_y, V) to first order; NaN without an error
    and where the states are NaN. lbo.scoring.lateral.body_error fits them by maximum
    likelihood, calibrated where the observer reads them (at its estimate): errors that grow
    with the state give a relative part, errors of one size the floor alone. A checkpoint's
    stored error that is not a 2 x 2 matrix of finite, non-negative numbers is refused in one
    line naming it."""
    from types import SimpleNamespace

    from lbo.models.checkpoint import LATERAL_ERROR, stored_lateral_error
    from lbo.scoring.lateral import body_error
    from lbo.serve.estimate import lateral_variance, side_slip

    error = np.array([[1e-4, 0.02], [1e-8, 0.0]])
    body = np.array([[0.5, 0.2], [np.nan, np.nan], [-1.0, 0.0]])
    speed = np.array([10.0, 10.0, 4.0])
    states = side_slip(body, speed)
    var = lateral_variance(error, states, speed)
    assert var.shape == (3, 3) and np.isnan(var[1]).all()
    np.testing.assert_allclose(var[[0, 2], 1], [1e-4 + 0.02 * 0.25, 1e-4 + 0.02 * 1.0])
    np.testing.assert_allclose(var[[0, 2], 2], [1e-8, 1e-8])
    eps = 1e-6  # beta's slope in v_y, by a difference
    slope = (np.arctan2(body[:, 0] + eps, speed) - np.arctan2(body[:, 0] - eps, speed)) / (2 * eps)
    np.testing.assert_allclose(var[[0, 2], 0], slope[[0, 2]] ** 2 * var[[0, 2], 1], rtol=1e-6)
    assert np.isnan(lateral_variance(None, states, speed)).all()

    rng = np.random.default_rng(0)
    v_y = rng.uniform(-0.3, 0.3, (4, 5000))
    sd = np.sqrt(1e-6 + 0.03 * v_y ** 2)  # errors 17% of v_y, over a floor of 1 mm/s
    arr = SimpleNamespace(lateral=np.stack([v_y, 0 * v_y], -1), mask=np.ones(v_y.shape, bool))
    off = arr.lateral + np.stack([sd * rng.standard_normal(v_y.shape), 0 * v_y + 1e-3], -1)
    fit = body_error(off, arr)
    # read at the estimate, as an observer reads it: calibrated overall and from the
    # straightest quarter of the rows to the hardest cornering one
    e2 = (off[..., 0] - v_y) ** 2
    nees = e2 / (fit[0, 0] + fit[0, 1] * off[..., 0] ** 2)
    assert nees.mean() == pytest.approx(1.0, rel=0.05) and fit[0, 1] > 0.02
    size = np.abs(off[..., 0])
    for q in range(4):  # within 0.4-1.6 in each quarter; one variance for all is not
        quarter = (size >= np.quantile(size, q / 4)) & (size <= np.quantile(size, (q + 1) / 4))
        assert 0.4 < nees[quarter].mean() < 1.6, (q, nees[quarter].mean())
    assert (e2 / e2.mean())[size <= np.quantile(size, 0.25)].mean() < 0.2
    np.testing.assert_allclose(fit[1], [1e-6, 0.0], atol=1e-12)  # r off by 1e-3: a floor

    assert stored_lateral_error("x", {}) is None
    np.testing.assert_array_equal(stored_lateral_error("x", {LATERAL_ERROR: error.tolist()}),
                                  error)
    for bad in ([[1.0, -2.0], [3.0, 4.0]], [[np.nan, 0], [0, 1]], [1.0, 2.0], "big",
                [["a", 0], [0, 1]]):
        with pytest.raises(LboError, match=r"^checkpoint c.ckpt: its stored meta.lateral_error "
                                           r"is not the body's error as a 2 x 2 matrix of "
                                           r"finite, non-negative numbers") as e:
            stored_lateral_error("checkpoint c.ckpt", {LATERAL_ERROR: bad})
        assert "\n" not in str(e.value)
