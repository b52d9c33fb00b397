import numpy as np
import pytest

from helpers import compose_cfg
from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.sim.noise import PRESETS, Noise
from lbo.sim.vehicle import Vehicle, f, jacobian, measure, simulate, step


def test_straight_line():
    v, psi, n = 10.0, 0.3, 500
    u = np.tile([v, 0.0], (2, n, 1))
    z = simulate(np.array([[1.0, 2.0, psi]] * 2), u, 0.02, 2.7)
    k = np.arange(n) * 0.02
    np.testing.assert_allclose(z[0, :, 0], 1.0 + v * np.cos(psi) * k, atol=1e-9)
    np.testing.assert_allclose(z[0, :, 1], 2.0 + v * np.sin(psi) * k, atol=1e-9)
    np.testing.assert_allclose(z[0, :, 2], psi)


def test_constant_steering_closes_a_circle_of_radius_L_over_tan_delta():
    dt, L, v, n = 0.02, 2.7, 5.0, 900  # n steps make exactly one turn
    dpsi = 2 * np.pi / n
    delta = np.arctan(L * dpsi / (v * dt))
    z = simulate(np.zeros((1, 3)), np.tile([v, delta], (1, n + 1, 1)), dt, L)[0]
    np.testing.assert_allclose(z[-1, :2], [0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(z[-1, 2], 2 * np.pi, atol=1e-9)
    radius = L / np.tan(delta)
    centre = z[:-1, :2].mean(axis=0)  # one full turn, each point once
    np.testing.assert_allclose(np.hypot(*(z[:, :2] - centre).T), radius, rtol=1e-4)


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(1)
    z = rng.normal(size=(20, 3))
    u = np.column_stack([rng.uniform(1, 20, 20), rng.uniform(-0.4, 0.4, 20)])
    jac = jacobian(z, u, 0.02)
    eps = 1e-6
    for i in range(3):
        dz = np.zeros(3)
        dz[i] = eps
        fd = (step(z + dz, u, 0.02, 2.7) - step(z - dz, u, 0.02, 2.7)) / (2 * eps)
        np.testing.assert_allclose(jac[:, :, i], fd, atol=1e-7)


def test_f_is_vectorised_over_batches():
    """f on a (4, 5) batch of states and inputs is f of each row on its own: no row takes
    another's state, input or heading."""
    rng = np.random.default_rng(3)
    z = np.column_stack([rng.normal(0, 50, 20), rng.normal(0, 50, 20),
                         rng.uniform(-np.pi, np.pi, 20)]).reshape(4, 5, 3)
    u = np.column_stack([rng.uniform(1, 20, 20), rng.uniform(-0.4, 0.4, 20)]).reshape(4, 5, 2)
    batch = f(z, u, 2.7)
    assert batch.shape == (4, 5, 3)
    rows = np.array([[f(z[i, j], u[i, j], 2.7) for j in range(5)] for i in range(4)])
    np.testing.assert_allclose(batch, rows, rtol=0, atol=1e-12)
    assert len(np.unique(rows.reshape(-1, 3).round(6), axis=0)) == 20  # 20 distinct rows


def test_noise_statistics_of_a_large_sample():
    noise = Noise.preset("paper")
    rng = np.random.default_rng(0)
    z = np.zeros((200_000, 3))
    m = measure(z, noise.meas(3.0), rng)
    np.testing.assert_allclose(m.std(axis=0), 3.0 * np.array([1.0, 1.0, 17.4e-3]), rtol=0.01)
    np.testing.assert_allclose(m.mean(axis=0), 0.0, atol=0.02)
    w = np.diff(simulate(np.zeros((1, 3)), np.zeros((1, 100_001, 2)), 0.02, 2.7,
                         np.array(noise.process_sigma), rng)[0], axis=0)
    np.testing.assert_allclose(w.std(axis=0), [0.2 / 3, 0.2 / 3, 3.4e-3 / 3], rtol=0.01)


def test_presets_read_the_table_two_ways():
    paper, literal = Noise.preset("paper"), Noise.preset("literal")
    np.testing.assert_allclose(paper.measurement_sigma, [1.0, 1.0, 0.0174])
    np.testing.assert_allclose(literal.measurement_sigma, [1 / 3, 1 / 3, 0.0058])
    np.testing.assert_allclose(paper.process_sigma, literal.process_sigma)
    np.testing.assert_allclose(paper.R(2.0), np.diag([4.0, 4.0, 4 * 0.0174**2]))


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_hydra_noise_configs_match_the_presets(name):
    cfg = compose_cfg("datagen", [f"noise={name}"])
    from_cfg, preset = Noise.from_cfg(cfg.noise), Noise.preset(name)
    assert from_cfg.process_sigma == preset.process_sigma  # exactly: same data, same hashes
    assert from_cfg.measurement_sigma == preset.measurement_sigma


def test_wrap_angle_range():
    a = np.array([-np.pi, np.pi, 3 * np.pi, -3 * np.pi + 0.1, 0.0])
    w = wrap_angle(a)
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)


@pytest.mark.parametrize("kwargs, field", [
    ({"dt": 0.0}, "vehicle.dt"), ({"wheelbase": -1.0}, "vehicle.wheelbase"),
    ({"v_min": 5.0, "v_max": 2.0}, "vehicle.v_max"), ({"delta_max": 2.0}, "vehicle.delta_max")])
def test_bad_vehicle_parameters_name_the_field(kwargs, field):
    with pytest.raises(LboError, match=field):
        Vehicle(**kwargs)


def test_negative_noise_is_refused():
    with pytest.raises(LboError, match="noise.measurement_sigma"):
        Noise((0.1, 0.1, 0.001), (1.0, -1.0, 0.01))
    with pytest.raises(LboError, match="alpha"):
        Noise.preset("paper").meas(-1.0)
    with pytest.raises(LboError, match="noise preset"):
        Noise.preset("nope")
