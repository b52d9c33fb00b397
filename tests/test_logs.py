"""data=logs: training, tuning and evaluation on a user's own logs; fine-tuning (init_from)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from helpers import compose_cfg, store_client
from lbo.core.errors import LboError

COLUMNS = ["t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi"]
DT = 0.02


@pytest.fixture(scope="module")
def logs(smoke_data, tmp_path_factory) -> Path:
    """Logs made from the smoke test set: each manoeuvre at each alpha is one log (600 rows
    at 50 Hz). Training: alpha 0, 2, 4, 5, 6; validation: alpha 1; test: alpha 3."""
    root = tmp_path_factory.mktemp("logs")
    test = pd.read_parquet(smoke_data / "test.parquet")
    for part in ("train", "val", "test"):
        (root / part).mkdir()
    for (traj, alpha), g in test.groupby(["traj", "alpha"]):
        part = "val" if alpha == 1.0 else "test" if alpha == 3.0 else "train"
        log = g.sort_values("k")[COLUMNS]
        if part == "test" and traj == 2:
            log.to_parquet(root / part / f"m{traj}_a{alpha:g}.parquet", index=False)
        else:
            log.to_csv(root / part / f"m{traj}_a{alpha:g}.csv", index=False)
    return root


def logs_cfg(root: Path, tmp: Path, *overrides: str, name: str = "train"):
    return compose_cfg(name, ["experiment=smoke", "data=logs", f"data.train=[{root}/train]",
                              f"data.val=[{root}/val]", f"data.test=[{root}/test/*]",
                              "data.run_in=100", f"data.root={tmp}/data",
                              f"output_dir={tmp}/out", *overrides])


def built(cfg):
    from lbo.logs import sets as logs

    spec = logs.spec_from_cfg(cfg)
    folder, sets, _ = logs.build(spec, progress=False)
    return spec, folder, sets


def test_the_sets_are_the_logs_split_by_file(logs, tmp_path):
    spec, folder, sets = built(logs_cfg(logs, tmp_path))
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["kind"] == "logs"
    files = {part: [Path(f["file"]).name for f in manifest["files"][part]] for part in sets}
    assert files["test"] == ["m0_a3.csv", "m1_a3.csv", "m2_a3.parquet"]
    assert len(files["train"]) == 15 and len(files["val"]) == 3
    assert not set(files["train"]) & (set(files["val"]) | set(files["test"]))
    source = pd.read_parquet(logs / "test" / "m2_a3.parquet")
    rows = sets["test"][sets["test"]["file"] == 2]
    np.testing.assert_array_equal(rows[["x", "y", "psi", "x_m", "V"]].to_numpy(),
                                  source[["x", "y", "psi", "x_m", "V"]].to_numpy())
    # scored from run_in on; alpha is the level the reference measures in the file
    assert (rows["scored"] == (rows["k"] >= 100)).all()
    assert rows["alpha"].iloc[0] == pytest.approx(3.0, rel=0.08)
    assert sets["val"]["alpha"].iloc[0] == pytest.approx(1.0, rel=0.08)
    # the same logs give the same folder, byte for byte; another byte gives another folder
    spec2, folder2, _ = built(logs_cfg(logs, tmp_path))
    assert folder2 == folder
    first = (folder / "train.parquet").read_bytes()
    shutil_copy = tmp_path / "copy"
    shutil_copy.mkdir()
    for p in (logs / "train").iterdir():
        (shutil_copy / p.name).write_bytes(p.read_bytes())
    changed = shutil_copy / "m0_a0.csv"
    df = pd.read_csv(changed)
    df.loc[3, "V"] += 0.001
    df.to_csv(changed, index=False)
    spec3 = built(logs_cfg(logs, tmp_path, f"data.train=[{shutil_copy}]"))[0]
    assert spec3.digest != spec.digest
    # and resume=true never reuses a run trained on the logs' old contents
    from lbo.learn.identity import config_hash

    cfg_copy = logs_cfg(logs, tmp_path, f"data.train=[{shutil_copy}]")
    before = config_hash(cfg_copy)
    df.loc[4, "V"] += 0.001
    df.to_csv(changed, index=False)
    assert config_hash(cfg_copy) != before
    assert (folder / "train.parquet").read_bytes() == first


@pytest.mark.parametrize("damage", ["cut", "replaced"])
def test_a_logs_cache_cut_short_or_replaced_is_said_and_read_again(logs, tmp_path, capsys,
                                                                  damage):
    """A set of a logs cache cut short under its final name (a disk error, an interrupted copy
    of data/), or written over by another program, is named in one line and rebuilt from the
    logs, byte for byte, instead of ending the command in a pyarrow traceback."""
    _, folder, _ = built(logs_cfg(logs, tmp_path))
    test = folder / "test.parquet"
    before = test.read_bytes()
    if damage == "cut":
        test.write_bytes(before[:len(before) // 2])
    else:
        pd.DataFrame({"t": [0.0], "x": [1.0]}).to_parquet(test)
    capsys.readouterr()
    _, again, sets = built(logs_cfg(logs, tmp_path))
    out = capsys.readouterr().out
    assert again == folder and f"{test}: " in out and "reading the logs again" in out
    assert test.read_bytes() == before
    assert len(sets["test"]) > 0


def write(df: pd.DataFrame, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(path, index=False)
    return path


def test_gaps_and_dt_jumps_cut_a_log_into_segments(logs, tmp_path):
    """Windows never cross a gap in time or a jump in dt: each stretch is a trajectory of its
    own, its k from 0; with resample=true a gap up to max_gap is interpolated instead."""
    log = pd.read_csv(logs / "train" / "m0_a2.csv")
    gap = log.drop(index=range(200, 215)).reset_index(drop=True)  # 0.3 s without rows
    jump = log.copy()
    jump.loc[400:, "t"] = log["t"].iloc[400] + (log["t"].iloc[400:] - log["t"].iloc[400]) * 1.5
    write(gap, tmp_path / "cut" / "gap.csv")
    write(jump, tmp_path / "cut" / "jump.csv")
    cfg = logs_cfg(logs, tmp_path, f"data.train=[{tmp_path}/cut]")
    _, _, sets = built(cfg)
    tr = sets["train"]
    lengths = tr.groupby(["file", "traj"]).size().to_list()
    # jump.csv: the rows after the jump are at 0.03 s, not dt: left out without resample
    assert lengths == [200, len(gap) - 200, 401]
    assert (tr.groupby("traj")["k"].min() == 0).all()
    steps = tr.groupby("traj")["t"].diff().dropna()
    assert np.allclose(steps, DT)  # inside a segment, every step is dt: no window crosses a cut
    # resample=true: the 0.3 s gap (< max_gap 0.5 s) is interpolated, a 1 s gap cuts
    long_gap = log.drop(index=range(200, 250)).reset_index(drop=True)
    write(long_gap, tmp_path / "rs" / "long_gap.csv")
    write(gap, tmp_path / "rs" / "gap.csv")
    cfg = logs_cfg(logs, tmp_path, f"data.train=[{tmp_path}/rs]", "data.resample=true")
    _, _, sets = built(cfg)
    per_file = sets["train"].groupby("file")["traj"].nunique().to_list()
    assert per_file == [1, 2]  # gap.csv, long_gap.csv (sorted by name)
    write(jump, tmp_path / "rs2" / "jump.csv")
    _, _, sets = built(logs_cfg(logs, tmp_path, f"data.train=[{tmp_path}/rs2]",
                                "data.resample=true"))
    t = jump["t"].to_numpy()
    assert len(sets["train"]) == int(np.floor((t[-1] - t[0]) / DT + 1e-9)) + 1


def test_resample_puts_a_10_hz_log_on_the_vehicles_grid(logs, tmp_path):
    log = pd.read_csv(logs / "train" / "m0_a2.csv").iloc[::5].reset_index(drop=True)
    write(log, tmp_path / "slow" / "ten_hz.csv")
    with pytest.raises(LboError, match="resample=true"):
        built(logs_cfg(logs, tmp_path, f"data.train=[{tmp_path}/slow]"))
    _, _, sets = built(logs_cfg(logs, tmp_path, f"data.train=[{tmp_path}/slow]",
                                "data.resample=true"))
    tr = sets["train"]
    assert len(tr) == (len(log) - 1) * 5 + 1
    fix = tr[["x_m", "y_m", "psi_m"]].notna().all(axis=1).to_numpy()
    assert fix.sum() == len(log) and fix[::5].all()  # fixes land on their rows, never made up


def test_windows_never_cross_a_file_and_training_reads_stored_noise(logs, tmp_path):
    from lbo.learn.builders import datamodule, prepare_data

    cfg = logs_cfg(logs, tmp_path, "train_noise=stored", "window=40")
    dm = datamodule(cfg, prepare_data(cfg)[0])
    train = pd.read_parquet(dm.folder / "train.parquet")
    ends = dm.train_set.ends.numpy()
    starts = ends - 40 + 1
    traj = train["traj"].to_numpy()
    assert (traj[starts] == traj[ends]).all()
    assert len(ends) == sum(max(n - 39, 0) for n in train.groupby("traj").size())
    win, state, _ = dm.train_set.batch(np.arange(8), dm.train_set.generator)
    # stored: the windows hold the logged measurements as they are
    np.testing.assert_array_equal(win[:, -1, :3].numpy(),
                                  train[["x_m", "y_m", "psi_m"]].to_numpy()[ends[:8]])


@pytest.mark.slow
def test_train_on_logs_scores_the_test_files_against_their_peers(logs, tmp_path, tracking,
                                                                 one_torch_thread):
    import mlflow

    from lbo.train import train

    cfg = logs_cfg(logs, tmp_path, "train_noise=stored")
    metrics = train(cfg)
    table = pd.read_csv(tmp_path / "out" / "evaluation.csv")
    assert set(table["observer"]) == {"cnn-N20", "ekf", "adaptive", "ukf"}
    assert set(table["file"]) == {"all", *(str(p) for p in sorted((logs / "test").iterdir()))}
    pooled = table[table["file"] == "all"].set_index("observer")
    assert pooled.loc["ekf", "nrmse"] == pytest.approx(1.0)  # normalised by the EKF
    assert pooled.loc["cnn-N20", "ratio_to_ekf"] == pytest.approx(pooled.loc["cnn-N20", "nrmse"])
    assert pooled.loc["cnn-N20", "ratio_to_adaptive"] == pytest.approx(
        pooled.loc["cnn-N20", "nrmse"] / pooled.loc["adaptive", "nrmse"])
    # the adaptive EKF learns the test logs' alpha=3 noise: better than R at alpha=1
    assert pooled.loc["adaptive", "nrmse"] < 0.95
    assert metrics["test_nrmse"] == pytest.approx(pooled.loc["cnn-N20", "nrmse"])
    # across the test logs: the mean and the worst of its ratio to the EKF on each
    mine = table[(table["observer"] == "cnn-N20") & (table["file"] != "all")]["ratio_to_ekf"]
    assert len(mine) == 3
    assert metrics["test_drives_vs_ekf_mean"] == pytest.approx(mine.mean())
    assert metrics["test_drives_vs_ekf_worst"] == pytest.approx(mine.max())
    run = mlflow.MlflowClient(tracking).get_run(metrics["run_id"])
    assert {"test_nrmse", "test_rmse_x", "ratio_to_ekf", "ratio_to_adaptive",
            "test_drives_vs_ekf_worst"} <= set(run.data.metrics)
    assert (tmp_path / "out" / "nrmse.png").stat().st_size > 0
    # fine-tuning from that run: it starts from its weights
    from lbo.learn.builders import build_net, initial_weights
    from lbo.tracking.artifacts import load_net

    cfg2 = logs_cfg(logs, tmp_path / "ft", "train_noise=paper", f"init_from={metrics['run_id']}")
    net = build_net(cfg2)
    state = initial_weights(cfg2, net)
    src, _ = load_net(metrics["run_id"])
    assert state.keys() == src.state_dict().keys()
    net.load_state_dict(state)
    for k, v in src.state_dict().items():
        assert np.array_equal(net.state_dict()[k].numpy(), v.numpy()), k
    # drawn noise over the logged truth trains too, and the run starts from those weights
    tuned = train(cfg2)
    assert np.isfinite(tuned["test_nrmse"])


def test_init_from_refuses_another_architecture_in_one_line(logs, tmp_path, smoke_data):
    from lbo.train import check

    ckpt = tmp_path / "cnn.ckpt"
    _save_checkpoint(ckpt, smoke_data)
    ok = logs_cfg(logs, tmp_path, f"init_from={ckpt}")
    check(ok)
    cases = [("model=lstm", "model=lstm"), ("window=40", "shape"),
             ("features=absolute", "features=absolute")]
    for override, text in cases:
        with pytest.raises(LboError, match=text) as e:
            check(logs_cfg(logs, tmp_path, f"init_from={ckpt}", override))
        assert "\n" not in str(e.value) and "init_from" in str(e.value)
    with pytest.raises(LboError, match="init_from: .*not found"):
        check(logs_cfg(logs, tmp_path, f"init_from={tmp_path}/none.ckpt"))


def _save_checkpoint(path: Path, smoke_data: Path) -> None:
    """An untrained smoke CNN (N=20), saved the way lbo.train saves its best checkpoint."""
    import torch

    from lbo.learn.builders import build_net, model_settings
    from lbo.models.net import CHECKPOINT_FORMAT
    from lbo.train import meta

    cfg = compose_cfg("train", ["experiment=smoke", f"data.root={smoke_data.parent}"])
    net = build_net(cfg)
    hp = {"model": model_settings(cfg), "window": cfg.model.window,
          "features": cfg.model.features,
          "fixes": False, "format": CHECKPOINT_FORMAT, "meta": meta(cfg, "x")}
    torch.save({"hyper_parameters": hp,
                "state_dict": {f"observer.{k}": v for k, v in net.state_dict().items()}}, path)


@pytest.mark.slow
def test_tune_on_logs_and_a_study_keeps_to_its_logs(logs, tmp_path, tracking, one_torch_thread):
    from lbo.tune import tune

    base = [f"tune.storage=sqlite:///{tmp_path}/optuna.db", "tune.n_trials=1",
            "hparams_search=cnn", f"tune.handoff={tmp_path}/tuned/cnn.yaml"]
    result = tune(logs_cfg(logs, tmp_path, *base, name="tune"))
    assert np.isfinite(result["best_value"])
    other = tmp_path / "other"
    other.mkdir()
    for p in sorted((logs / "train").iterdir())[:5]:
        (other / p.name).write_bytes(p.read_bytes())
    with pytest.raises(LboError, match="tune.study_name: .*other logs"):
        tune(logs_cfg(logs, tmp_path, *base, f"data.train=[{other}]", name="tune"))


def test_evaluate_scores_the_peers_on_the_test_logs(logs, tmp_path):
    from lbo.evaluate import evaluate

    cfg = compose_cfg("evaluate", ["data=logs", f"data.test=[{logs}/test]", "data.run_in=100",
                                   f"data.root={tmp_path}/data", f"output_dir={tmp_path}"])
    csv = evaluate(cfg)
    table = pd.read_csv(csv)
    assert set(table["observer"]) == {"ekf", "adaptive", "ukf"}  # no oracle, no pcrb: no alpha
    assert len(table) == 3 * 4  # pooled and per file
    assert (tmp_path / "nrmse_logs.png").is_file()
    # across the test logs: each one's ratio to the EKF on it, their mean and the worst
    per_log = table[table["file"] != "all"]
    names = [Path(f).name for f in dict.fromkeys(per_log["file"])]
    text = (tmp_path / "drives.md").read_text()
    assert text.splitlines()[0] == "| estimator | " + " | ".join(names) + " | mean | worst |"
    for observer, rows in per_log.groupby("observer"):
        ratios = rows["ratio_to_ekf"].to_numpy()
        line = next(r for r in text.splitlines() if r.startswith(f"| {observer} |"))
        cells = [float(c) for c in line.strip("| ").split(" | ")[1:]]
        assert cells == pytest.approx([*np.round(ratios, 3), round(ratios.mean(), 3),
                                       round(ratios.max(), 3)], abs=1e-9), observer
    assert set(per_log.loc[per_log["observer"] == "ekf", "ratio_to_ekf"]) == {1.0}
    assert per_log["ratio_to_ekf"].nunique() > 3  # the peers differ from log to log


def test_an_observers_run_is_told_its_mean_and_worst_across_the_test_logs(tmp_path,
                                                                         monkeypatch):
    """log_to_run on a user's logs: the pooled NRMSE, and with two logs or more the mean and
    the worst of its ratio to the EKF on each (a real MLflow store)."""

    from lbo.evaluate import log_to_run

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    client = store_client(uri)
    run = client.create_run(client.create_experiment("e", f"{tmp_path / 'art'}")).info.run_id
    pd.DataFrame({"observer": ["mine"] * 3 + ["ekf"] * 3,
                  "file": ["all", "/a/d1.csv", "/b/d2.csv"] * 2,
                  "nrmse": [0.9, 0.8, 1.1, 1.0, 1.0, 1.0],
                  "ratio_to_ekf": [0.9, 0.8, 1.1, 1.0, 1.0, 1.0]}).to_csv(
        tmp_path / "evaluation.csv", index=False)
    log_to_run(run, run, "mine", tmp_path / "evaluation.csv", "logs")
    logged = client.get_run(run).data.metrics
    assert logged == pytest.approx({"eval_logs_nrmse": 0.9,
                                    "eval_logs_drives_vs_ekf_mean": 0.95,
                                    "eval_logs_drives_vs_ekf_worst": 1.1})


def ten_hz_fixes(logs: Path, folder: Path) -> Path:
    """Four of the training logs with a fix at every fifth row only (10 Hz), in ``folder``."""
    for p in sorted((logs / "train").glob("*.csv"))[:4]:
        df = pd.read_csv(p)
        df.loc[df.index % 5 != 0, ["x_m", "y_m", "psi_m"]] = np.nan
        write(df, folder / p.name)
    return folder


def test_logs_with_gnss_slower_than_the_inputs_train_with_fix_rates(logs, tmp_path):
    from lbo.learn.builders import datamodule, prepare_data

    slow = ten_hz_fixes(logs, tmp_path / "slow")
    cfg = logs_cfg(logs, tmp_path, f"data.train=[{slow}]", "train_noise=stored")
    with pytest.raises(LboError, match="fix_rates"):
        datamodule(cfg, prepare_data(cfg)[0])
    # fix_rates=[50] drops nothing more: the windows hold the logs' own gaps, as they are
    cfg = logs_cfg(logs, tmp_path, f"data.train=[{slow}]", "train_noise=stored",
                   "fix_rates=[50]")
    dm = datamodule(cfg, prepare_data(cfg)[0])
    win, _, _ = dm.train_set.batch(np.arange(64), dm.train_set.generator)
    assert win[..., 0].isnan().float().mean().item() == pytest.approx(0.8, abs=0.03)


def test_dropping_fixes_on_logs_with_gaps_never_leaves_a_window_without_a_fix(logs, tmp_path):
    from lbo.learn.builders import datamodule, prepare_data

    slow = ten_hz_fixes(logs, tmp_path / "slow")
    cfg = logs_cfg(logs, tmp_path, f"data.train=[{slow}]", "train_noise=stored",
                   "fix_rates=[1]")
    dm = datamodule(cfg, prepare_data(cfg)[0])
    win, _, _ = dm.train_set.batch(np.arange(len(dm.train_set)), dm.train_set.generator)
    fixes = torch.isfinite(win[..., 0])
    assert fixes.any(1).all()
    assert fixes.float().mean() < 0.19  # and the dropout still thins the logs' 20% of fixes
