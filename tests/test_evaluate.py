
import numpy as np
import pandas as pd
import pytest

from helpers import cli, compose_cfg
from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.evaluate import evaluate
from lbo.filters.kalman import ekf_batch
from lbo.filters.pcrb import pcrb
from lbo.scoring.grid import Q_GRID, classical, classical_table, load_test, reference, tuned_oracle
from lbo.scoring.metrics import SCORE_COLUMNS
from lbo.sim import schema
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle, measure, simulate

VEHICLE, NOISE = Vehicle(), Noise.preset("paper")


@pytest.fixture(scope="module")
def smoke_table(smoke_data):
    arr = load_test(smoke_data / "test.parquet")
    return classical_table(arr, VEHICLE, NOISE, ["ekf", "oracle", "adaptive", "pcrb"])


def curve(table, name):
    return table[table["observer"] == name].set_index("alpha")["nrmse"]


def test_orderings_on_the_smoke_grid(smoke_table):
    ekf, oracle = curve(smoke_table, "ekf"), curve(smoke_table, "oracle")
    adaptive, bound = curve(smoke_table, "adaptive"), curve(smoke_table, "pcrb")
    assert (oracle <= ekf + 1e-9).all()
    assert (oracle[oracle.index >= 3] < 0.8 * ekf[ekf.index >= 3]).all()
    # one noise draw per level over 1,500 correlated points: "within noise" is a few percent,
    # and up to ~15 % for the bound at high alpha (its expectation is tested below)
    assert (bound <= 1.15 * oracle + 1e-9).all()
    assert (oracle <= 1.05 * adaptive).all()
    assert (adaptive[adaptive.index >= 3] < 0.85 * ekf[ekf.index >= 3]).all()


def test_pcrb_is_a_floor_in_expectation(smoke_data):
    """The bound is on the MSE averaged over process and measurement noise: re-simulate both."""
    arr = load_test(smoke_data / "test.parquet")
    one = np.isclose(arr.alpha, 0.0)
    z, u, mask = arr.z[one], arr.u[one], arr.mask[one]
    rng = np.random.default_rng(0)
    for alpha in (1.0, 3.0, 6.0):
        R = NOISE.R(alpha)
        bound = pcrb(z, u, VEHICLE, NOISE.Q, R, rng=1)[mask].mean(axis=0)
        mse = []
        for _ in range(16):
            zk = simulate(z[:, 0], u, VEHICLE.dt, VEHICLE.wheelbase, NOISE.process_sigma, rng)
            err = ekf_batch(measure(zk, NOISE.meas(alpha), rng), u, VEHICLE, NOISE.Q, R).mean - zk
            err[..., 2] = wrap_angle(err[..., 2])
            mse.append((err[mask] ** 2).mean(axis=0))
        ratio = np.mean(mse, axis=0) / bound
        assert np.all(ratio > 0.95), (alpha, ratio)
        assert np.all(ratio < 1.3), (alpha, ratio)


def test_the_ekf_reference_is_filterpys_rmse_at_alpha_1(smoke_data, smoke_table):
    """E_ref re-derived independently: filterpy's EKF on every alpha=1 trajectory, and the
    pooled RMSE written out in numpy; and the paper's constants as printed in its Table I."""
    from lbo.filters.reference import run_filterpy_ekf

    arr = load_test(smoke_data / "test.parquet")
    at1 = np.flatnonzero(np.isclose(arr.alpha, 1.0))
    sq, n = np.zeros(3), 0
    for g in at1:
        est = run_filterpy_ekf(arr.m[g], arr.u[g], VEHICLE, NOISE.Q, NOISE.R(1.0))
        err = (est - arr.z[g])[arr.mask[g]]
        err[:, 2] = (err[:, 2] + np.pi) % (2 * np.pi) - np.pi
        sq, n = sq + (err**2).sum(0), n + len(err)
    expected = np.sqrt(sq / n)
    np.testing.assert_allclose(reference(arr, VEHICLE, NOISE, "ekf"), expected, rtol=1e-9)
    row = smoke_table[(smoke_table["observer"] == "ekf") & (smoke_table["alpha"] == 1.0)]
    np.testing.assert_allclose(row[["rmse_x", "rmse_y", "rmse_psi"]].to_numpy()[0], expected,
                               rtol=1e-9)
    # the paper's Table I: EKF at alpha=1, x 0.24 m, y 0.23 m, psi 4.1 mrad
    np.testing.assert_array_equal(reference(arr, VEHICLE, NOISE, "paper"), [0.24, 0.23, 0.0041])
    with pytest.raises(LboError, match="metric.reference"):
        reference(arr, VEHICLE, NOISE, "mine")


def test_alpha_zero_oracle_is_exact(smoke_data):
    arr = load_test(smoke_data / "test.parquet")
    est = classical("oracle", arr, VEHICLE, NOISE)
    zero = np.isclose(arr.alpha, 0.0)
    err = (est - arr.z)[zero][arr.mask[zero]]
    err[:, 2] = wrap_angle(err[:, 2])
    np.testing.assert_allclose(err, 0.0, atol=1e-6)


def test_the_tuned_oracle_is_the_best_of_its_q_grid_at_every_level(smoke_data):
    arr = load_test(smoke_data / "test.parquet")
    ref = reference(arr, VEHICLE, NOISE)
    est, chosen = tuned_oracle(arr, VEHICLE, NOISE, ref)
    tuned = classical_table(arr, VEHICLE, NOISE, ["oracle", "oracle_tuned"], ref)
    assert list(chosen["alpha"]) == sorted(set(arr.alpha))
    assert chosen["position"].isin(Q_GRID[0]).all() and chosen["heading"].isin(Q_GRID[1]).all()
    # the oracle's own Q (factors 1, 1) is on the grid: tuning never does worse than it
    assert (curve(tuned, "oracle_tuned") <= curve(tuned, "oracle") + 1e-12).all()
    # each level's winner is that level's EKF with the chosen Q, scored as any observer
    row = chosen.iloc[-1]
    Q = np.diag(np.square(np.asarray(NOISE.process_sigma)
                          * [row.position, row.position, row.heading]))
    at = np.isclose(arr.alpha, row.alpha)
    R = np.einsum("g,ij->gij", arr.alpha[at] ** 2, NOISE.R(1.0))
    np.testing.assert_allclose(est[at], ekf_batch(arr.m[at], arr.u[at], VEHICLE, Q, R).mean)


def test_pcrb_bounds_the_kinematic_truth_with_its_own_process_noise(smoke_data):
    from lbo.sim.truth import Truth, from_cfg

    arr = load_test(smoke_data / "test.parquet")
    paper = classical("pcrb", arr, VEHICLE, NOISE, truth=Truth())
    calm = classical("pcrb", arr, VEHICLE, NOISE, truth=Truth(process_scale=0.1))
    noisy = arr.mask & (arr.alpha > 0)[:, None]
    assert (calm[noisy] < paper[noisy]).all()
    car = from_cfg({"name": "dynamic"}, None, 2.7)
    with pytest.raises(LboError, match="pcrb: the bound is the kinematic bicycle's"):
        classical("pcrb", arr, VEHICLE, NOISE, truth=car)


def eval_cfg(tmp_path, smoke_data, *overrides):
    return compose_cfg("evaluate", ["data=smoke", f"data.root={smoke_data.parent}",
                                    f"output_dir={tmp_path / 'out'}",
                                    "observers=[ekf,oracle,adaptive,pcrb]", *overrides])


def test_evaluate_writes_the_table_and_the_figure(tmp_path, smoke_data, capsys):
    csv = evaluate(eval_cfg(tmp_path, smoke_data))
    table = pd.read_csv(csv)
    assert list(table.columns) == list(SCORE_COLUMNS)
    assert set(table["observer"]) == {"ekf", "oracle", "adaptive", "pcrb"}
    assert len(table) == 4 * 7
    assert (tmp_path / "out" / "nrmse_classical.png").stat().st_size > 10_000
    assert capsys.readouterr().out.strip().splitlines()[-1] == f"evaluation: {csv}"


def broken_copies(smoke_data, tmp_path):
    df = pd.read_parquet(smoke_data / "test.parquet")
    no_col = tmp_path / "no_psi_m.parquet"
    schema.write_set(df.drop(columns=["psi_m"]), no_col)
    nan = df.copy()
    nan.loc[5, "y_m"] = np.nan
    with_nan = tmp_path / "nan.parquet"
    schema.write_set(nan, with_nan)
    return no_col, with_nan


def test_bad_data_files_name_the_column_and_write_nothing(tmp_path, smoke_data):
    no_col, with_nan = broken_copies(smoke_data, tmp_path)
    with pytest.raises(LboError, match="missing column 'psi_m'"):
        evaluate(eval_cfg(tmp_path, smoke_data, f"test_file={no_col}"))
    # x_m without y_m is refused (all three empty: no fix, allowed)
    with pytest.raises(LboError, match=r"row 5 has x_m without y_m"):
        evaluate(eval_cfg(tmp_path, smoke_data, f"test_file={with_nan}"))
    with pytest.raises(LboError, match="unknown observer 'kalman'"):
        evaluate(eval_cfg(tmp_path, smoke_data, "observers=[ekf,kalman]"))
    assert not (tmp_path / "out").exists()


def test_cli_exit_code_and_one_line_error(tmp_path, smoke_data):
    no_col, _ = broken_copies(smoke_data, tmp_path)
    out = tmp_path / "cli"
    res = cli("lbo.evaluate", "data=smoke", f"data.root={smoke_data.parent}",
              f"test_file={no_col}", f"hydra.run.dir={out}", "observers=[ekf]")
    assert res.returncode == 2
    assert res.stderr.strip().splitlines()[-1].startswith("error: ")
    assert "missing column 'psi_m'" in res.stderr
    assert not (out / "evaluation.csv").exists()
