"""The observer that learns the model error (experiment=dynamic: filternet with a learned
single-track body and drift states) at smoke scale, end to end: trained, scored beside
the kinematic EKFs and the EKF told the car, reported, streamed on a log."""

import functools
import math

import mlflow
import numpy as np
import pandas as pd
import pytest
import torch

from helpers import compose_cfg, observed, train_in_own_store
from helpers.shared import once
from lbo.core.errors import LboError
from lbo.learn.jobs import train_jobs
from lbo.learn.lightning_module import TrainingModule
from lbo.models import WindowFilter, build_model
from lbo.models.motion import BODY_PARAMETERS
from lbo.models.net import WindowNet
from lbo.scoring import report, studies
from lbo.serve.observer import Observer
from lbo.sim.dynamic import SingleTrack
from lbo.sim.dynamic import simulate as simulate_car

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SMOKE = ["data.train.n_traj=16", "data.train.duration=10.0", "data.test.alpha_step=1.0",
         "data.test.manoeuvres=[double_lane_change,hairpin,braking_in_bend]"]


@pytest.fixture(scope="module")
def dynamic(tmp_path_factory, worker_id, smoke_data):
    """experiment=dynamic trained for a few batches on a smoke-sized data=dynamic_drift (once
    for the run: the tests only read it)."""
    def make(tmp):
        cfg, out, uri = train_in_own_store(tmp, smoke_data, "experiment=dynamic",
                                           "data=dynamic_drift", *SMOKE, "window=60",
                                           "trainer.max_epochs=1",
                                           "trainer.limit_train_batches=4", "batch_size=32")
        return {"cfg": cfg, "out": out, "uri": uri, "dir": tmp / "out"}

    return once(tmp_path_factory, worker_id, "dynamic", make)


def test_experiment_trains_on_the_car_that_slips_and_scores_against_its_oracle(dynamic):
    cfg, out = dynamic["cfg"], dynamic["out"]
    assert (cfg.car.name, cfg.sensors.gnss_sigma, cfg.model.body, cfg.model.drift) == \
        ("dynamic", 0.5, "single_track", True)
    table = pd.read_csv(dynamic["dir"] / "evaluation.csv")
    assert set(table["observer"]) == {"filternet-N60", "ekf", "oracle", "adaptive",
                                      "oracle_tuned", "oracle_dynamic"}
    run = mlflow.MlflowClient(dynamic["uri"]).get_run(out["run_id"])
    assert run.data.metrics["worst_dynamic_oracle_ratio"] > 0
    psi = table.pivot_table(index="alpha", columns="observer", values="rmse_psi")
    # the EKF told the car knows where its heading goes in a corner; the kinematic one does not
    assert (psi.loc[1:, "oracle_dynamic"] < 0.5 * psi.loc[1:, "oracle"]).all()
    # a few batches moved the learned body and the drift off their starting values
    net = Observer.load(out["checkpoint"]).net.net
    assert net.body_parameters() != build_model("filternet", 60,
                                                body="single_track").body_parameters()
    assert net.log_drift_tau.item() != pytest.approx(math.log(10.0 / 0.02), abs=1e-9)


def test_its_lateral_states_are_scored_beside_the_oracle_told_the_car(dynamic, smoke_data,
                                                                      tmp_path, capsys):
    """``lbo.evaluate learned=[...]`` on the car that slips: lateral.csv holds the learned
    observer's beta, v_y and r (the ``[v_y, r]`` its single-track body carries) at every
    level, beside the EKF told the car; a kinematic-body observer carries none."""
    from types import SimpleNamespace

    from lbo.evaluate import evaluate
    from lbo.scoring import lateral
    from lbo.scoring.grid import learned_nets, load_test

    ckpt = dynamic["out"]["checkpoint"]
    evaluate(compose_cfg("evaluate", ["data=dynamic_drift", *SMOKE, "observers=[ekf]",
                                      f"data.root={smoke_data.parent}", f"learned=[{ckpt}]",
                                      f"output_dir={tmp_path}"]))
    assert "(a learned observer's where it carries a single-track body)" in \
        capsys.readouterr().out
    table = pd.read_csv(tmp_path / "lateral.csv")
    assert list(dict.fromkeys(table["observer"])) == ["filternet-N60", "oracle_dynamic",
                                                      "kinematic", "zero"]
    mine = table[table["observer"] == "filternet-N60"].set_index("alpha")
    assert len(mine) == 7 and mine[["rmse_beta", "rmse_vy", "rmse_r"]].notna().all().all()
    # beta's variance is made of its body's error on the validation set, read from the
    # checkpoint: the same NEES at every level (the body is driven by the inputs, not the fixes)
    assert (mine["nees_beta"] > 0).all() and mine["nees_beta"].nunique() == 1
    kin = table[table["observer"] == "kinematic"].set_index("alpha")
    assert (mine["rmse_r"] < 3 * kin["rmse_r"]).all()  # a yaw rate of the car's size
    # the body is the recursive form's: its r follows the car's yaw (v tan(delta) / L at
    # the start); none where the pose has no estimate
    net = learned_nets([ckpt])["filternet-N60"]
    arr = load_test(next(smoke_data.parent.glob("dynamic_drift-*")) / "test.parquet")
    body = lateral.carried(net, arr)
    assert body.shape == (*arr.m.shape[:2], 2) and np.isfinite(body[arr.mask]).all()
    r_start = arr.u[:, 0, 0] * np.tan(arr.u[:, 0, 1]) / net.net.wheelbase
    np.testing.assert_allclose(body[:, 0, 1], r_start, rtol=1e-9, atol=1e-12)
    assert lateral.carries(net)
    assert not lateral.carries(SimpleNamespace(net=build_model("filternet", 60)))


def test_its_checkpoint_holds_its_bodys_error_on_the_validation_set(dynamic, smoke_data):
    """The training measured the error of the body's ``[v_y, r]`` against the validation
    set's own after its validation, logged its RMSE and wrote the error into the checkpoint:
    measured again here from the checkpoint's weights, the same matrix."""
    from lbo.models.checkpoint import LATERAL_ERROR, hyperparameters
    from lbo.scoring import lateral
    from lbo.scoring.grid import load_test

    ckpt = dynamic["out"]["checkpoint"]
    stored = np.array(hyperparameters(ckpt)["meta"][LATERAL_ERROR])
    net = Observer.load(ckpt).net
    np.testing.assert_array_equal(net.lateral_error, stored)
    val = load_test(next(smoke_data.parent.glob("dynamic_drift-*")) / "val.parquet")
    assert val.lateral is not None
    again = lateral.body_error(lateral.carried(net, val), val)
    np.testing.assert_allclose(again, stored, rtol=1e-6)
    assert (stored >= 0).all() and (stored.sum(1) > 0).all()
    body = lateral.carried(net, val)
    rmse = np.sqrt(np.mean((body - val.lateral)[val.mask] ** 2, axis=0))
    metrics = mlflow.MlflowClient(dynamic["uri"]).get_run(dynamic["out"]["run_id"]).data.metrics
    assert metrics["val_body_rmse_vy"] == pytest.approx(rmse[0], rel=1e-5)
    assert metrics["val_body_rmse_r"] == pytest.approx(rmse[1], rel=1e-5)


def test_a_kalmannet_around_the_body_has_its_error_measured_as_lbo_train_measures_it(
        dynamic, smoke_data):
    """The callback lbo.train runs (``LateralError``) on a KalmanNet peer around the
    single-track body, which is carried otherwise than the window filter: after a
    validation, the error of its body on the validation set, logged and written into a
    checkpoint's metadata (a copy: the module's own is left as built); nothing in the sanity
    check, nor for a peer without a body."""
    from types import SimpleNamespace

    from lbo.learn.callbacks import LateralError
    from lbo.models.checkpoint import LATERAL_ERROR
    from lbo.scoring import lateral
    from lbo.scoring.grid import load_test

    folder = next(smoke_data.parent.glob("dynamic_drift-*"))
    logged: dict = {}
    net = WindowNet("kalmannet", 60, "frame", body="single_track")
    module = SimpleNamespace(observer=net, device=torch.device("cpu"), log_dict=logged.update)
    trainer = SimpleNamespace(sanity_checking=True, datamodule=SimpleNamespace(folder=folder))
    measure = LateralError()
    measure.on_validation_epoch_end(trainer, module)
    assert measure.error is None and not logged
    trainer.sanity_checking = False
    measure.on_validation_epoch_end(trainer, module)
    val = load_test(folder / "val.parquet")
    np.testing.assert_allclose(measure.error, lateral.body_error(lateral.carried(net, val), val))
    assert logged["val_body_rmse_r"] == pytest.approx(np.sqrt(np.mean(
        (lateral.carried(net, val) - val.lateral)[..., 1][val.mask] ** 2)))
    meta = {"seed": 0}
    saved = {"hyper_parameters": {"meta": meta}}
    measure.on_save_checkpoint(trainer, module, saved)
    assert saved["hyper_parameters"]["meta"] == {"seed": 0,
                                                 LATERAL_ERROR: measure.error.tolist()}
    assert meta == {"seed": 0}
    plain = LateralError()
    plain.on_validation_epoch_end(trainer, SimpleNamespace(
        observer=WindowNet("kalmannet", 60, "frame"), device=torch.device("cpu")))
    assert plain.error is None


def test_report_section_where_learning_beats_the_model(dynamic, tmp_path):
    table = pd.read_csv(dynamic["dir"] / "evaluation.csv")
    box = table[table["observer"] == "filternet-N60"].assign(observer="cnn-N80")
    box["nrmse"] *= 1.5  # a black-box peer's rows beside it
    peer = table[table["observer"] == "filternet-N60"].assign(observer="kalmannet-N60")
    peer["nrmse"] *= 1.2  # and a learned peer's
    table = pd.concat([table, box, peer], ignore_index=True)
    classical = table[table["observer"].isin(["ekf", "oracle"])].copy()
    files = report.write(tmp_path, "smoke", classical, {}, {},
                         sections=[studies.Dynamic("dynamic_drift", table)])
    text = (tmp_path / "report.md").read_text()
    assert "## Where learning beats the model: `data=dynamic_drift`" in text
    assert "times the dynamic oracle's" in text and "![dynamic_drift](nrmse_dynamic_drift.png)" \
        in text
    assert tmp_path / "nrmse_dynamic_drift.png" in files
    assert "| alpha | filternet-N60 | cnn-N80 | kalmannet-N60 | ekf |" in text
    assert "`cnn-N80`" in text and "kalmannet-N60 / oracle_dynamic" in text
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "dynamic_drift.csv"), table)
    s = studies.dynamic_summary(table)
    assert (s["observer"], s["black_boxes"], s["peers"]) == ("filternet-N60", ["cnn-N80"],
                                                             ["kalmannet-N60"])
    nr = table.pivot_table(index="alpha", columns="observer", values="nrmse").loc[0.25:]
    lo, hi = s["peers_vs_dynamic"]["kalmannet-N60"]
    assert hi == pytest.approx((nr["kalmannet-N60"] / nr["oracle_dynamic"]).max())
    assert f"trained as it is, over the dynamic oracle's: `kalmannet-N60` {lo:.2f} to " \
        f"{hi:.2f}." in text
    assert s["vs_dynamic"][1] == pytest.approx((nr["filternet-N60"] / nr["oracle_dynamic"]).max())
    assert s["vs_tuned"][0] == pytest.approx((nr["filternet-N60"] / nr["oracle_tuned"]).min())
    assert "times the kinematic EKF's with Q tuned in hindsight" in text
    assert "filternet-N60 / oracle_tuned" in text


def test_the_observer_streams_a_log_of_the_car(dynamic, tmp_path):
    from lbo.simulate import simulate

    log = simulate(compose_cfg("simulate", ["data=dynamic_drift", "manoeuvre=hairpin",
                                            "alpha=2"]))
    obs = Observer.load(dynamic["out"]["checkpoint"])
    m, u = log[["x_m", "y_m", "psi_m"]].to_numpy(), log[["V", "delta"]].to_numpy()
    est, valid = obs.run(m, u)
    assert valid.sum() == len(log) - 59 and np.isfinite(est).all()
    streamed = np.array([obs.step(m[k], u[k])[0] for k in range(80)])
    np.testing.assert_allclose(streamed[59:], est[59:80], atol=1e-6)
    truth = log[["x", "y"]].to_numpy()
    assert np.sqrt(np.mean((est[valid, :2] - truth[valid]) ** 2)) < 2.0  # metres, at alpha 2


def test_observe_writes_the_lateral_states_its_recursive_form_carries(dynamic, tmp_path):
    """``lbo.observe ... form=recursive`` on a log of the car that slips adds beta, v_y and r:
    the body its filter carries, as Observer.run and Observer.step give it (beta = atan2(v_y,
    V)), its yaw rate turning with the car, and their variances; the window form, which starts
    the body afresh in each window, adds none."""
    from lbo.simulate import simulate

    log = simulate(compose_cfg("simulate", ["data=dynamic_drift", "manoeuvre=hairpin",
                                            "alpha=2"]))
    log.to_csv(tmp_path / "log.csv", index=False)
    ckpt = dynamic["out"]["checkpoint"]
    observed(tmp_path / "log.csv", tmp_path / "carried.csv", "form=recursive", observer=ckpt)
    observed(tmp_path / "log.csv", tmp_path / "window.csv", observer=ckpt)
    lateral = ["beta", "v_y", "r"]
    out = pd.read_csv(tmp_path / "carried.csv")
    assert set(lateral) <= set(out.columns)
    assert not set(lateral) & set(pd.read_csv(tmp_path / "window.csv").columns)
    obs = Observer.load(ckpt, form="recursive")
    assert obs.carries_lateral and not Observer.load(ckpt).carries_lateral
    m, u = log[["x_m", "y_m", "psi_m"]].to_numpy(), log[["V", "delta"]].to_numpy()
    found = obs.run(m, u)
    assert found.valid.all()
    np.testing.assert_allclose(out[lateral].to_numpy(), found.lateral, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out["beta"], np.arctan2(out["v_y"], log["V"]), atol=1e-12)
    streamed = np.array([obs.step(m[k], u[k]).lateral for k in range(80)])
    np.testing.assert_allclose(streamed, found.lateral[:80], rtol=0, atol=1e-9)
    turn = log["V"] * np.tan(log["delta"]) / obs.vehicle.wheelbase  # the bicycle's yaw rate
    assert np.corrcoef(out["r"], turn)[0, 1] > 0.9
    # with their variances, made of the body's error on the validation set (its checkpoint's):
    # a floor and a part that grows with the state, beta's v_y's through atan2(v_y, V)
    variances = ["var_beta", "var_v_y", "var_r"]
    error = obs.lateral_error
    assert error is not None and not set(variances) & set(pd.read_csv(tmp_path / "window.csv"))
    np.testing.assert_allclose(out[variances].to_numpy(), found.lateral_var, rtol=0, atol=1e-15)
    np.testing.assert_allclose(out["var_v_y"], error[0, 0] + error[0, 1] * out["v_y"] ** 2)
    np.testing.assert_allclose(out["var_r"], error[1, 0] + error[1, 1] * out["r"] ** 2)
    slope = log["V"] / (log["V"] ** 2 + out["v_y"] ** 2)
    np.testing.assert_allclose(out["var_beta"], slope ** 2 * out["var_v_y"], rtol=1e-12)
    obs.reset()
    np.testing.assert_allclose(np.array([obs.step(m[k], u[k]).lateral_var for k in range(80)]),
                               found.lateral_var[:80], rtol=1e-9)


def test_the_drift_calibration_benchmark_reads_the_run_and_prints_each_level(dynamic,
                                                                            monkeypatch, capsys):
    """``benchmarks/drift_calibration.py`` on the trained run: a row per level, the data's
    true sigmas beside the filter's, every share of the NEES finite and positive. Its
    ``main`` runs in this process with the arguments the command line gives it (the script
    folder on the path, as ``python benchmarks/drift_calibration.py`` puts it there): the
    test is about what it reads and prints, not the process, and saves an interpreter and
    lbo's imports."""
    from helpers.scripts import run_script
    from lbo.core.paths import REPO_ROOT

    lines = run_script(REPO_ROOT / "benchmarks" / "drift_calibration.py",
                       ["--run", str(dynamic["dir"]), "--alphas", "1", "3", "--data-root",
                        str(dynamic["cfg"].data.root)], monkeypatch, capsys).strip().splitlines()
    assert "white sigma 1.0 m, drift sigma 0.5 m at alpha = 1" in lines[0]
    # what the filter learned of the drift, read from its checkpoint, beside the data's
    net = Observer.load(dynamic["out"]["checkpoint"]).net.net
    tau, ratio = math.exp(net.log_drift_tau.item()) * 0.02, math.exp(net.log_drift_ratio.item())
    assert lines[1] == (f"learned: correlation time {tau:.2f} s, drift sigma {ratio:.3f} of "
                        f"the white sigma (data: 0.500)")
    rows = [[float(x) for x in line.split()] for line in lines[3:]]
    assert [r[0] for r in rows] == [1.0, 3.0]
    assert [(r[2], r[4]) for r in rows] == [(1.0, 0.5), (3.0, 1.5)]  # the data's sigmas
    assert all(math.isfinite(x) and x > 0 for r in rows for x in (r[1], r[3], *r[5:]))


def test_residual_and_drift_start_as_the_kinematic_window_filter():
    torch.manual_seed(0)
    plain = build_model("filternet", 40).double()
    rich = build_model("filternet", 40, residual=8, drift=True).double()
    rich.load_state_dict({**plain.state_dict(), **{k: v for k, v in rich.state_dict().items()
                                                   if k not in plain.state_dict()}})
    x = torch.randn(6, 40, 5, dtype=torch.float64) * 0.5
    x[..., 3], x[..., 4] = 8.0, 0.05 * torch.randn(6, 40, dtype=torch.float64)
    with torch.no_grad():
        rich.log_drift_ratio.fill_(-30.0)  # no drift: the two extra states never move
    torch.testing.assert_close(rich(x), plain(x), rtol=0, atol=1e-12)
    # without drift the extra values are not saved, so older checkpoints still load
    assert "log_drift_tau" not in plain.state_dict() and "log_drift_tau" in rich.state_dict()


def test_a_drift_correlation_time_given_is_held_and_saved():
    """``drift_tau`` (s) holds the drift's correlation time: not a parameter (no optimiser
    moves it), saved with the checkpoint, and the same filter as a learned one set to it."""
    torch.manual_seed(0)
    held = build_model("filternet", 40, drift=True, drift_tau=4.0).double()
    learned = build_model("filternet", 40, drift=True).double()
    assert "log_drift_tau" not in dict(held.named_parameters())
    assert "log_drift_tau" in dict(learned.named_parameters())
    assert held.state_dict()["log_drift_tau"].item() == pytest.approx(math.log(4.0 / 0.02))
    learned.load_state_dict(held.state_dict())  # the same keys either way
    x = torch.randn(6, 40, 5, dtype=torch.float64) * 0.5
    x[..., 3], x[..., 4] = 8.0, 0.05 * torch.randn(6, 40, dtype=torch.float64)
    torch.testing.assert_close(held(x), learned(x), rtol=0, atol=0)
    with torch.no_grad():
        learned.log_drift_tau.fill_(math.log(10.0 / 0.02))  # another time: another filter
    assert not torch.allclose(held(x), learned(x))


def _told_the_car(p: SingleTrack) -> WindowFilter:
    """A single-track window filter whose body has the car's own parameters."""
    net = build_model("filternet", 40, body="single_track").double()
    fzf, fzr = p.axle_loads
    with torch.no_grad():
        net.log_stiffness.copy_(torch.tensor([p.c_f, p.c_r]).log() - math.log(p.mass))
        net.log_peak.copy_(torch.tensor([p.mu * fzf, p.mu * fzr]).log() - math.log(p.mass))
        net.front_logit.fill_(math.log(p.l_f / p.l_r))
        net.log_gyration.fill_(math.log(p.yaw_inertia / p.mass / (p.l_f * p.l_r)))
        net.log_v_kinematic.fill_(math.log(p.v_kinematic))
    return net


def _open_loop(net: WindowFilter, s0: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The net's process model alone from the true states s0 (B, 5) over inputs u (B, T, 2):
    poses (B, T-1, 3) at steps 1 .. T-1."""
    z, body = torch.from_numpy(s0[:, :3]), torch.from_numpy(s0[:, 3:])
    if not net.single_track:
        body = net.body_start(torch.from_numpy(u[:, 0, 0]), torch.from_numpy(u[:, 0, 1]))
    out = []
    with torch.no_grad():
        for k in range(u.shape[1] - 1):
            v, delta = torch.from_numpy(u[:, k]).unbind(1)
            z, _, _, body = net.predict_pose(z, v, delta, body)
            out.append(z.numpy())
    return np.stack(out, 1)


def test_the_single_track_body_told_the_cars_parameters_follows_the_car():
    """Open loop over 20 s of weaving at 1 to 15 m/s: the learned body's equations with the
    car's parameters stay within 3 mrad of its heading; the kinematic bicycle is 10x off."""
    p = SingleTrack()
    t = np.arange(1000) * 0.02
    v = np.stack([3 + 2 * np.sin(0.5 * t), 9 + 6 * np.sin(0.3 * t), 9 + 6 * np.sin(0.3 * t)])
    delta = np.stack([0.2, 0.06, 0.12])[:, None] * np.sin(0.7 * t)
    u = np.stack([v, delta], -1)
    s = simulate_car(np.zeros((3, 3)), u, 0.02, p)
    told = np.abs(_open_loop(_told_the_car(p), s[:, 0], u) - s[:, 1:, :3])
    kinematic = np.abs(_open_loop(build_model("filternet", 40).double(), s[:, 0], u)
                       - s[:, 1:, :3])
    assert told[..., 2].max() < 3e-3 and told[..., :2].max() < 0.2
    assert (kinematic[..., 2].max(1) > 10 * told[..., 2].max(1)).all()
    assert _told_the_car(p).body_parameters()["l_f"] == pytest.approx(p.l_f)


@pytest.mark.parametrize("kwargs, field", [({"residual": -1}, "model.residual"),
                                           ({"residual": 2.5}, "model.residual"),
                                           ({"drift": "yes"}, "model.drift"),
                                           ({"body": "dynamic"}, "model.body"),
                                           ({"body": "single_track", "residual": 8},
                                            "model.residual"),
                                           ({"body_lr": 0}, "model.body_lr"),
                                           ({"body_lr": -2.0}, "model.body_lr"),
                                           ({"body_lr": True}, "model.body_lr"),
                                           ({"body_lr": "fast"}, "model.body_lr"),
                                           ({"drift": True, "drift_tau": 0}, "model.drift_tau"),
                                           ({"drift": True, "drift_tau": -5.0},
                                            "model.drift_tau"),
                                           ({"drift": True, "drift_tau": math.inf},
                                            "model.drift_tau"),
                                           ({"drift": True, "drift_tau": True},
                                            "model.drift_tau"),
                                           ({"drift": True, "drift_tau": "10 s"},
                                            "model.drift_tau"),
                                           ({"drift_tau": 10.0}, "model.drift_tau"),
                                           ({"body_rear": 1.5}, "model.body_rear"),
                                           ({"body": "single_track", "body_rear": 0.0},
                                            "model.body_rear"),
                                           ({"body": "single_track", "body_rear": 2.7},
                                            "model.body_rear"),
                                           ({"body": "single_track", "body_rear": "1.5 m"},
                                            "model.body_rear")])
def test_bad_residual_drift_or_body_names_the_field(kwargs, field):
    with pytest.raises(LboError, match=field) as e:
        build_model("filternet", 40, **kwargs)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("name", ["filternet", "kalmannet", "split_kalmannet"])
def test_a_centre_of_gravity_given_is_held_through_training_and_saved(name):
    """``model.body_rear``: the body's l_r is the one given, no parameter the optimiser moves,
    and a checkpoint's state holds it; the other constants still learn."""
    module = TrainingModule({"name": name, "body": "single_track", "body_rear": 1.5},
                            40, features="frame",
                            optimizer=functools.partial(torch.optim.Adam, lr=1e-2))
    net = module.observer.net
    assert net.body_parameters()["l_r"] == pytest.approx(1.5)
    assert "front_logit" not in dict(net.named_parameters())
    opt = module.configure_optimizers()
    x = torch.randn(8, 40, 5, generator=torch.Generator().manual_seed(0)) * 0.3
    x[..., 3], x[..., 4] = 10.0, 0.1
    before = net.body_parameters()
    net(x).pow(2).sum().backward()
    opt.step()
    after = net.body_parameters()
    assert after["l_r"] == pytest.approx(1.5) and after["k_f"] != before["k_f"]
    fresh = build_model(name, 40, body="single_track")
    fresh.load_state_dict(net.state_dict())  # a learned body reads the held one's checkpoint
    assert fresh.body_parameters()["l_r"] == pytest.approx(1.5)


@pytest.mark.parametrize("body_lr", [1.0, 3.0])
def test_the_body_learns_at_body_lr_times_the_optimisers_rate(body_lr):
    module = TrainingModule({"name": "filternet", "body": "single_track", "body_lr": body_lr},
                            40, features="frame",
                            optimizer=functools.partial(torch.optim.Adam, lr=1e-3))
    net = module.observer.net
    before = {name: p.detach().clone() for name, p in net.named_parameters()}
    opt = module.configure_optimizers()
    torch.manual_seed(0)
    x = torch.randn(8, 40, 5) * 0.3
    x[..., 3], x[..., 4] = 10.0, 0.1  # a corner at speed: every body constant has a gradient
    net(x).pow(2).sum().backward()
    opt.step()
    # Adam's first step moves every parameter with a gradient by its group's rate
    for name, p in net.named_parameters():
        moved = (p.detach() - before[name]).abs()
        rate = 1e-3 * (body_lr if name in BODY_PARAMETERS else 1.0)
        moving = p.grad.abs() > 1e-12
        assert torch.allclose(moved[moving], torch.full_like(moved[moving], rate), rtol=1e-3), name
    assert sum(p.numel() for g in opt.param_groups for p in g["params"]) == \
        sum(p.numel() for p in net.parameters())


def test_reproduce_trains_the_study_beside_the_paper_at_quick_scale(tmp_path):
    cfg = compose_cfg("reproduce", ["scale=quick", "study=all", f"report_dir={tmp_path}"])
    jobs = {j.key: list(j.overrides) for j in train_jobs(cfg, tmp_path)}
    kinds = {j.key: (j.kind, j.data) for j in train_jobs(cfg, tmp_path)}
    assert kinds["dynamic-cnn"] == ("dynamic", "dynamic") and kinds["robust"] == ("robust", None)
    assert kinds["literal-cnn-N60"] == ("literal", None)
    assert jobs["dynamic"][:2] == ["experiment=dynamic", "data=dynamic"]
    assert jobs["dynamic_drift"][:2] == ["experiment=dynamic", "data=dynamic_drift"]
    assert "resume=true" in jobs["dynamic"]
    # every run logs where the report reads it: the command's tracking_uri, passed on only
    # where a run would not find it itself
    given = compose_cfg("reproduce", ["scale=quick", "tracking_uri=sqlite:///elsewhere.db"])
    assert all(compose_cfg("train", [o for o in j.overrides if not o.startswith(
                   ("+tuned", "hydra."))]).logger.tracking_uri == "sqlite:///elsewhere.db"
               for j in train_jobs(given, tmp_path))
    assert not any(o.startswith("logger.tracking_uri") for o in jobs["dynamic"])
    for model in ("cnn", "lstm"):  # the black-box peers, on the first data set only
        assert jobs[f"dynamic-{model}"][:3] == ["experiment=dynamic_blackbox", f"model={model}",
                                                "data=dynamic"]
        assert f"dynamic_drift-{model}" not in jobs
    # every run has its own name in MLflow: the literal protocol's beside the paper's
    names = {k: compose_cfg("train", [o for o in v if not o.startswith(("+tuned", "hydra."))]
                            ).logger.run_name for k, v in jobs.items()}
    assert names["literal-cnn-N60"] == "literal-cnn-N60" and names["cnn-N60"] == "cnn-N60"
    assert names["dynamic"].startswith("dynamic-filternet-N")
    assert names["dynamic-cnn"].startswith("dynamic-cnn-N") and names["robust"].startswith(
        "robust-filternet-N")
    assert len(set(names.values())) == len(names)
    smoke = {j.key for j in train_jobs(compose_cfg("reproduce", ["scale=smoke", "study=all"]),
                                       tmp_path)}
    assert "dynamic" not in smoke  # the smoke reproduction stays seconds long
    assert not any(k.startswith("robust-") for k in jobs)  # the peers: paper scale only
    # study= picks the parts: the paper's by default, the car that slips alone, or both
    def keys(*more: str) -> set[str]:
        return {j.key for j in train_jobs(compose_cfg("reproduce", ["scale=quick", *more]),
                                          tmp_path)}
    dynamic = {"dynamic", "dynamic_drift", "dynamic-cnn", "dynamic-lstm"}
    assert keys() == keys("study=paper") == set(jobs) - dynamic
    assert keys("study=dynamic") == dynamic
    with pytest.raises(LboError, match=r"^study must be paper, dynamic or all, got 'cars'$"):
        train_jobs(compose_cfg("reproduce", ["study=cars"]), tmp_path)


def test_reproduce_trains_the_learned_peers_as_the_robust_observer_at_paper_scale(tmp_path):
    """KalmanNet and Split-KalmanNet: the robust observer's experiment, data set and budget,
    each its own run folder and MLflow name, scored in its section of the report; and around
    the single-track body beside the car-that-slips observer."""
    cfg = compose_cfg("reproduce", ["scale=paper", "study=all", f"report_dir={tmp_path}"])
    jobs = {j.key: j for j in train_jobs(cfg, tmp_path)}
    robust = list(jobs["robust"].overrides)
    for model in ("kalmannet", "split_kalmannet"):
        job = jobs[f"robust-{model}"]
        assert job.kind == "robust"
        assert list(job.overrides) == [robust[0], f"model={model}", *robust[1:-1],
                                       f"output_dir={tmp_path / 'runs' / job.key}"]
        name = compose_cfg("train", list(job.overrides)).logger.run_name
        assert name == f"robust-{model}-N100"
    # around the single-track body, on the first car-that-slips data set, as its observer is
    dynamic = list(jobs["dynamic"].overrides)
    for model in ("kalmannet", "split_kalmannet"):
        job = jobs[f"dynamic-{model}"]
        assert (job.kind, job.data) == ("dynamic", "dynamic")
        assert list(job.overrides) == [dynamic[0], f"model={model}", "~model.drift",
                                       *dynamic[1:-1], f"output_dir={tmp_path / 'runs' / job.key}"]
        c = compose_cfg("train", list(job.overrides))
        assert c.model.body == "single_track" and "drift" not in c.model
        assert c.logger.run_name == f"dynamic-{model}-N400"
        assert f"dynamic_drift-{model}" not in jobs
    off = compose_cfg("reproduce", ["scale=paper", "robust=false"])
    assert not any(j.kind == "robust" for j in train_jobs(off, tmp_path))


@pytest.mark.parametrize("kwargs, form", [({}, "recursive"),
                                          ({"body": "single_track"}, "window"),
                                          ({"drift": True}, "window"),
                                          ({"residual": 8}, "window")])
def test_a_window_filter_with_a_learned_process_model_runs_in_its_window_form(kwargs, form):
    net = WindowNet("filternet", 40, features="frame", **kwargs)
    assert Observer.from_net(net).form == form
