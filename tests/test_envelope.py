"""A learned observer knows the range of inputs it was trained on, and says when a log leaves it.

The audit's case: a CNN trained on 1-25 m/s, run on a drive at 60 m/s, gave every estimate
``valid=true`` at 8 times the EKF's position error, and nothing said the speed was outside
what it had seen. The checkpoint now stores the envelope of its training inputs (speed,
steering, alpha, fix rate), and ``lbo.observe`` / ``Observer`` warn or mark the rows outside.
"""

from __future__ import annotations

import re
import warnings

import numpy as np
import pandas as pd
import pytest
import torch

from helpers import observe
from lbo.core.errors import LboError
from lbo.models.envelope import Envelope, alpha_estimates, fix_spacing
from lbo.serve.observer import EnvelopeWarning, Observer
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle, measure, simulate

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SIGMA = np.asarray(Noise.preset("paper").measurement_sigma)


@pytest.fixture(scope="module")
def cnn(smoke_cnn):
    """One smoke CNN (N=20), trained on the smoke friction circle at alpha = 1."""
    return smoke_cnn["checkpoint"]


def drive(speed: float, steer: float = 0.02, alpha: float = 1.0, steps: int = 600,
          seed: int = 0) -> pd.DataFrame:
    """A log of a car at a constant ``speed`` (m/s) and steering (rad), fixes at alpha."""
    rng = np.random.default_rng(seed)
    u = np.tile([speed, steer], (1, steps, 1)).astype(float)
    z = simulate(np.zeros((1, 3)), u, 0.02, 2.7)[0]
    m = measure(z, alpha * SIGMA, rng)
    return pd.DataFrame({"t": np.arange(steps) * 0.02, "x_m": m[:, 0], "y_m": m[:, 1],
                         "psi_m": m[:, 2], "V": u[0, :, 0], "delta": u[0, :, 1],
                         "x": z[:, 0], "y": z[:, 1], "psi": z[:, 2]})


def arrays(df: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    return (df[["x_m", "y_m", "psi_m"]].to_numpy(copy=True),
            df[["V", "delta"]].to_numpy(copy=True))


# --- what training stores -------------------------------------------------------------------


def test_the_checkpoint_stores_the_envelope_of_its_training_inputs(cnn, smoke_data):
    meta = torch.load(cnn, map_location="cpu", weights_only=True)["hyper_parameters"]["meta"]
    env = Envelope.from_dict(meta["envelope"])
    train = pd.read_parquet(smoke_data / "train.parquet")
    assert env.speed == pytest.approx((train["V"].min(), train["V"].max()))
    assert env.steering == pytest.approx((train["delta"].min(), train["delta"].max()))
    assert env.alpha == (1.0, 1.0)  # the smoke set's stored draw
    assert env.fix_period == (1.0, 1.0)  # a fix at every step
    assert Observer.load(cnn).envelope == env


# --- the estimates behind the check ---------------------------------------------------------


@pytest.mark.parametrize("alpha", [0.5, 1.0, 3.0, 6.0])
@pytest.mark.parametrize("period", [1, 5])
def test_alpha_is_estimated_from_the_fixes_at_any_fix_rate(alpha, period):
    df = drive(12.0, steer=0.05, alpha=alpha, steps=3000, seed=int(alpha * 10) + period)
    m, u = arrays(df)
    m[np.arange(len(m)) % period != 0] = np.nan  # GNSS slower than the inputs
    est = alpha_estimates(m, u, 0.02, 2.7, float(SIGMA[0]))
    judged = est[np.isfinite(est)]
    assert len(judged) > len(est) / 2
    assert np.median(judged) == pytest.approx(alpha, rel=0.1)
    assert np.all(np.abs(judged / alpha - 1) < 0.3)  # inside the check's slack


def test_fix_spacing_is_the_mean_over_the_last_window():
    fix = np.zeros(40, bool)
    fix[::5] = True
    s = fix_spacing(fix, 10)
    assert np.isnan(s[:9]).all() and np.allclose(s[9:], 5.0)
    fix[20:] = False
    assert np.isinf(fix_spacing(fix, 10)[-1])


def test_each_field_is_flagged_beyond_its_slack_only():
    env = Envelope(speed=(1.0, 25.0), steering=(-0.5, 0.5), alpha=(1.0, 1.0), fix_period=(1.0, 1.0))
    kw = {"dt": 0.02, "wheelbase": 2.7, "sigma": float(SIGMA[0]), "window": 20}
    inside = env.check(*arrays(drive(20.0)), **kw)
    assert not inside.outside.any()
    fast = env.check(*arrays(drive(60.0)), **kw)
    assert fast.speed.all() and not fast.steering.any() and not fast.alpha.any()
    noisy = env.check(*arrays(drive(15.0, alpha=4.0, steps=1500)), **kw)
    assert not noisy.alpha[:51].any()  # too few fix triples yet to judge
    assert noisy.alpha[200:].all() and not noisy.speed.any()
    assert set(noisy.reasons()[200:]) == {"alpha"}
    m, u = arrays(drive(15.0))
    m[np.arange(len(m)) % 5 != 0] = np.nan  # 10 Hz fixes on an observer trained at 50 Hz
    sparse = env.check(m, u, **kw)
    assert sparse.fix_period[19:].all() and not sparse.fix_period[:19].any()


def test_unknown_alpha_is_not_checked():
    env = Envelope(speed=(1.0, 25.0), steering=(-0.5, 0.5), alpha=None, fix_period=(1.0, 1.0))
    check = env.check(*arrays(drive(15.0, alpha=6.0)), dt=0.02, wheelbase=2.7, sigma=1.0,
                      window=20)
    assert not check.outside.any()


@pytest.mark.parametrize("stored, message", [
    ({"speed": [25.0, 1.0], "steering": [-0.5, 0.5], "alpha": None, "fix_period": [1, 1]},
     "envelope.speed: expected [low, high], two finite numbers with low <= high"),
    ({"speed": [1.0, 25.0]}, "envelope: expected the keys speed, steering, alpha, fix_period"),
])
def test_a_damaged_stored_envelope_is_one_line(stored, message):
    with pytest.raises(LboError, match=re.escape(message)) as err:
        Envelope.from_dict(stored)
    assert "\n" not in str(err.value)


def test_streaming_flags_equal_the_batch_flags():
    env = Envelope(speed=(1.0, 25.0), steering=(-0.3, 0.3), alpha=(0.5, 2.0), fix_period=(1.0, 2.0))
    rng = np.random.default_rng(3)
    df = drive(20.0, alpha=1.0, steps=900)
    m, u = arrays(df)
    u[:, 0] += np.linspace(0, 15, len(u))  # leaves the speed range on the way
    u[300:320, 1] = 0.4  # a burst of steering beyond it
    m[400:] += rng.standard_normal((500, 3)) * 5.0 * SIGMA  # the noise grows
    m[rng.random(len(m)) < 0.3] = np.nan  # irregular fixes
    kw = {"dt": 0.02, "wheelbase": 2.7, "sigma": float(SIGMA[0]), "window": 20}
    batch = env.check(m, u, **kw)
    stream = env.stream(**kw)
    rows = [stream(None if np.isnan(m[k, 0]) else m[k], u[k]) for k in range(len(m))]
    assert [",".join(r) for r in rows] == list(batch.reasons())
    assert batch.speed.any() and batch.steering.any() and batch.alpha.any()


# --- what the user sees -----------------------------------------------------------------------


def test_observe_warns_about_a_drive_beyond_the_trained_speed(cnn, tmp_path):
    log = tmp_path / "fast.csv"
    drive(60.0).to_csv(log, index=False)
    res = observe(f"observer={cnn}", f"input={log}", f"output={tmp_path / 'est.csv'}")
    assert res.returncode == 0, res.stderr[-2000:]
    assert re.search(r"warning: 600 of 600 rows outside the trained speed 1\.\.2\d\.?\d* m/s "
                     r"\(this log: 60\.\.60", res.stdout), res.stdout
    out = pd.read_csv(tmp_path / "est.csv", keep_default_na=False)
    assert set(out["outside"]) == {"speed"}
    assert out["valid"].iloc[19:].all()  # warn: the estimates stay valid

    res = observe(f"observer={cnn}", f"input={log}", f"output={tmp_path / 'marked.csv'}",
                  "envelope=mark")
    assert res.returncode == 0, res.stderr[-2000:]
    assert not pd.read_csv(tmp_path / "marked.csv")["valid"].any()
    assert "marked valid=false" in res.stdout


def test_a_drive_inside_the_envelope_is_not_flagged(cnn, tmp_path):
    log = tmp_path / "ok.csv"
    drive(15.0).to_csv(log, index=False)
    res = observe(f"observer={cnn}", f"input={log}", f"output={tmp_path / 'est.csv'}",
                  "envelope=mark")
    assert res.returncode == 0, res.stderr[-2000:]
    assert "outside the trained" not in res.stdout
    out = pd.read_csv(tmp_path / "est.csv", keep_default_na=False)
    assert set(out["outside"]) == {""} and out["valid"].iloc[19:].all()


def test_observer_step_warns_once_or_marks(cnn):
    m, u = arrays(drive(60.0, steps=40))
    obs = Observer.load(cnn)
    with pytest.warns(EnvelopeWarning, match="step 0: outside the training envelope: speed") \
            as caught:
        steps = [obs.step(m[k], u[k]) for k in range(40)]
    assert len(caught) == 1  # once per field, not once per step
    assert steps[-1].valid and steps[-1].outside == ("speed",)
    marked = Observer.load(cnn, envelope_mode="mark")
    est = [marked.step(m[k], u[k]) for k in range(40)]
    assert not any(e.valid for e in est)
    assert est[-1].reason.startswith("outside the training envelope: speed")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        off = Observer.load(cnn, envelope_mode="off")
        assert off.step(m[0], u[0]).outside == ()
        off.run(m, u)


def test_run_marks_the_same_rows_as_step(cnn):
    df = drive(20.0, steps=200)
    m, u = arrays(df)
    u[100:, 0] = 60.0
    obs = Observer.load(cnn, envelope_mode="mark")
    _, valid = obs.run(m, u)
    stepped = np.array([obs.step(m[k], u[k]).valid for k in range(len(m))])
    assert np.array_equal(valid, stepped)
    assert valid[19:100].all() and not valid[100:].any()


def test_a_bad_envelope_mode_is_one_line(cnn, tmp_path):
    with pytest.raises(LboError, match=r"^envelope: expected one of warn, mark, off, got 'loud'$"):
        Observer.load(cnn, envelope_mode="loud")
    log = tmp_path / "ok.csv"
    drive(15.0, steps=50).to_csv(log, index=False)
    res = observe(f"observer={cnn}", f"input={log}", f"output={tmp_path / 'e.csv'}",
                  "envelope=loud")
    assert res.returncode == 2 and "envelope: expected one of warn, mark, off" in res.stderr
    assert not (tmp_path / "e.csv").exists()


def test_a_checkpoint_without_an_envelope_still_loads(cnn, tmp_path):
    ckpt = torch.load(cnn, map_location="cpu", weights_only=True)
    del ckpt["hyper_parameters"]["meta"]["envelope"]
    old = tmp_path / "old.ckpt"
    torch.save(ckpt, old)
    assert Observer.load(old).envelope is None
    log = tmp_path / "fast.csv"
    drive(60.0, steps=50).to_csv(log, index=False)
    res = observe(f"observer={old}", f"input={log}", f"output={tmp_path / 'e.csv'}")
    assert res.returncode == 0 and "envelope: not checked" in res.stdout


# --- steering past the checkpoint's limit (the audit's item 16) -------------------------------


def test_the_steering_advice_works_for_a_learned_observer(cnn, tmp_path):
    """A car whose lock is past 0.5 rad: the refusal advises vehicle.delta_max, and following
    that advice runs the learned observer, with the rows beyond its training flagged."""
    log = tmp_path / "lock.csv"
    drive(5.0, steer=0.6, steps=100).to_csv(log, index=False)
    out = tmp_path / "est.csv"
    refused = observe(f"observer={cnn}", f"input={log}", f"output={out}")
    assert refused.returncode == 2 and "set vehicle.delta_max" in refused.stderr
    assert not out.exists()
    res = observe(f"observer={cnn}", f"input={log}", f"output={out}", "vehicle.delta_max=0.7")
    assert res.returncode == 0, res.stderr[-2000:]
    assert "outside the trained steering -0.5..0.5 rad" in res.stdout
    assert set(pd.read_csv(out, keep_default_na=False)["outside"]) == {"steering"}
    # the library takes the same advice: a vehicle with the larger lock
    with pytest.warns(EnvelopeWarning, match="steering"):
        Observer.load(cnn, Vehicle(delta_max=0.7)).run(*arrays(pd.read_csv(log)))


def test_headings_on_another_branch_give_the_same_estimates(cnn):
    """A logger's accumulated heading (rad, any branch) is taken as the wrapped one, by run and
    by step alike, and the caller's arrays are left as they were."""
    m, u = arrays(drive(15.0, steps=60))
    laps = m.copy()
    laps[:, 2] += 4 * np.pi
    obs = Observer.load(cnn)
    est, valid = obs.run(m, u)
    est_laps, _ = obs.run(laps, u)
    np.testing.assert_allclose(est_laps, est, atol=1e-9)
    shifted = m.copy()
    shifted[:, 2] += 2 * np.pi * (m[:, 2] < 0)  # within [-2 pi, 2 pi], as step takes them
    before = shifted.copy()
    stepped = np.array([obs.step(shifted[k], u[k]).state for k in range(len(m))])
    np.testing.assert_allclose(stepped[valid], est[valid], atol=1e-6)
    np.testing.assert_array_equal(shifted, before)
