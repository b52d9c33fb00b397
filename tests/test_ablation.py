"""The paper-protocol ablation: sweeps expanded, variants named, minmax normalisation, the fit
of the paper's EKF, the variant table, and `python -m lbo.ablation` at smoke size."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest

from helpers import compose_cfg
from helpers.config import train_cfg
from lbo.ablation import expand, factors, jobs, label
from lbo.core.errors import LboError
from lbo.scoring import paper_protocol as pp


def test_expand_crosses_values_and_keeps_lists_whole():
    got = expand("model=cnn features=a,b seed=0,1 fix_rates=[50,10]")
    assert len(got) == 4
    assert ["model=cnn", "features=a", "seed=1", "fix_rates=[50,10]"] in got
    with pytest.raises(LboError, match="sweeps: expected key=value"):
        expand("model=cnn window")


def test_jobs_once_each_with_scale_and_resume():
    cfg = compose_cfg("ablation", ["scale=smoke",
                                   "sweeps=['model=cnn seed=0,1','model=cnn seed=1']"])
    got = jobs(cfg)
    assert len(got) == 2  # seed=1 is in both sweeps
    assert all(j[0] == "experiment=smoke" and "resume=true" in j for j in got)
    # its bars hidden; the store is the one a run finds itself, so none is passed on
    assert all("callbacks.progress_bar.refresh_rate=0" in j and
               not any(o.startswith("logger.tracking_uri") for o in j) for j in got)
    # a store given to the command is passed on to every run (only then: it may hold a password)
    given = compose_cfg("ablation", ["scale=smoke", "sweeps=['model=cnn seed=0,1']",
                                     "tracking_uri=sqlite:///elsewhere.db"])
    assert all("logger.tracking_uri=sqlite:///elsewhere.db" in j for j in jobs(given))


def test_variant_names_tell_the_factors_apart_but_not_the_seed():
    cnn = compose_cfg("train", ["model=cnn", "window=60", "features=frame",
                                "train_noise=stored", "model.activation=sigmoid", "seed=2"])
    f = factors(cnn)
    assert f["seed"] == 2
    assert label(f) == "cnn-N60 frame stored sigmoid standard"
    lstm = compose_cfg("train", ["model=lstm", "window=80", "normalisation=minmax"])
    assert label(factors(lstm)) == "lstm-N80 relative fresh minmax"  # no activation to vary


def test_training_length_in_passes_over_the_windows():
    from lbo.ablation import epochs

    assert epochs(compose_cfg("train", ["experiment=quick"])) == 3.0   # 6 x half an epoch
    assert epochs(compose_cfg("train", ["experiment=smoke"])) == 2.0   # 2 x 20 batches
    f = factors(compose_cfg("train", ["experiment=quick", "trainer.max_epochs=12",
                                      "trainer.limit_train_batches=1.0"]))
    assert label(f, 3.0).endswith("standard 12 epochs") and label(f, 12.0).endswith("standard")


def test_minmax_puts_the_training_windows_in_the_unit_box(tmp_path, smoke_data):
    import torch

    from lbo.learn.builders import build_net, datamodule
    from lbo.models.features import window_features

    cfg = train_cfg(tmp_path, smoke_data, "features=frame", "train_noise=stored")
    dm = datamodule(cfg, smoke_data)
    net = build_net(cfg)
    stats = dm.normalisation(net, "minmax", n=500)
    standard = dm.normalisation(net, "standard", n=500)
    assert not bool((stats["in_std"] == standard["in_std"]).all())

    g = torch.Generator(device=dm.device).manual_seed(dm.seed)
    pick = torch.randperm(len(dm.train_set), generator=g, device=dm.device)[:500]
    win, _, _ = dm.train_set.batch(pick, g)
    f = (window_features(win, "frame").reshape(-1, 5).cpu() - stats["in_mean"]) / stats["in_std"]
    assert f.min().item() == pytest.approx(0.0, abs=1e-12)
    assert f.max().item() == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(LboError, match="normalisation: expected one of"):
        dm.normalisation(net, "zscore")


def test_normalisation_is_checked_and_keeps_old_hashes(tmp_path, smoke_data):
    from omegaconf import open_dict

    from lbo.learn.layouts import hash_v1, upgraded
    from lbo.train import check, config_hash

    with pytest.raises(LboError, match=r"^model.normalisation: expected one of "
                                       r"\['standard', 'minmax'\]"):
        check(train_cfg(tmp_path, smoke_data, "normalisation=zscore"))
    standard = train_cfg(tmp_path, smoke_data)
    before = standard.copy()  # a config from before the setting existed
    with open_dict(before):
        before.model.pop("normalisation")
    assert hash_v1(standard) == hash_v1(before)  # the hash those runs carry (version 1)...
    assert config_hash(upgraded(before)) == config_hash(standard)  # ...migrated: standard's
    assert config_hash(train_cfg(tmp_path, smoke_data, "normalisation=minmax")) \
        != config_hash(standard)


@pytest.fixture(scope="module")
def smoke_test_arrays(smoke_data):
    from lbo.scoring.grid import load_test
    from lbo.sim.noise import Noise
    from lbo.sim.vehicle import Vehicle

    cfg = compose_cfg("train", ["experiment=smoke"])
    return load_test(smoke_data / "test.parquet"), Vehicle.from_cfg(cfg.vehicle), \
        Noise.from_cfg(cfg.noise)


def test_fit_finds_a_planted_ekf_setting(smoke_test_arrays):
    arr, vehicle, noise = smoke_test_arrays
    grid = ((1.0, 2.0), (1.0, 3.0))
    planted = pp.fit_paper_ekf(arr, vehicle, noise, grid)
    row = planted[(planted["q_position"] == 2.0) & (planted["q_heading"] == 3.0)].iloc[0]
    target = np.array([[row["x_1"], row["y_1"], row["psi_1"] / 1e3],
                       [row["x_6"], row["y_6"], row["psi_6"] / 1e3]])
    fit = pp.fit_paper_ekf(arr, vehicle, noise, grid, target=target)
    assert (fit.iloc[0]["q_position"], fit.iloc[0]["q_heading"]) == (2.0, 3.0)
    assert fit.iloc[0]["deviation"] < 1e-9
    assert (fit["deviation"].iloc[1:] > 0.01).all()
    # the linear filter's limit: its error grows at most as fast as the measurement noise
    assert (fit[["growth_x", "growth_y", "growth_psi"]] < 6.0).all().all()


def test_fit_needs_alpha_1_and_6(smoke_test_arrays):
    arr, vehicle, noise = smoke_test_arrays
    keep = ~np.isclose(arr.alpha, 6.0)
    sub = arr.take(keep)
    with pytest.raises(LboError, match="no trajectory at alpha = 6"):
        pp.fit_paper_ekf(sub, vehicle, noise, ((1.0,), (1.0,)))


def _rows(observer: str, alphas, rmse: np.ndarray, nrmse) -> pd.DataFrame:
    return pd.DataFrame({"observer": observer, "alpha": alphas, "rmse_x": rmse[:, 0],
                         "rmse_y": rmse[:, 1], "rmse_psi": rmse[:, 2], "nrmse": nrmse})


def test_paper_distance_is_the_largest_factor_either_way():
    paper = np.array([[0.28, 0.23, 11e-3], [0.91, 0.89, 20e-3]])
    exact = _rows("v", [1.0, 6.0], paper, [1.0, 2.0])
    assert pp.paper_distance(exact, "v", "cnn") == pytest.approx({"alpha1": 1.0, "alpha6": 1.0})
    off = _rows("v", [1.0, 6.0], paper * np.array([[1, 1, 0.5], [3, 1, 1]]), [1.0, 2.0])
    assert pp.paper_distance(off, "v", "cnn") == pytest.approx({"alpha1": 2.0, "alpha6": 3.0})
    assert np.isnan(pp.paper_distance(off[off["alpha"] == 1.0], "v", "cnn")["alpha6"])


def test_variant_table_averages_seeds_and_finds_crossovers():
    alphas = [1.0, 3.0, 6.0]
    ones = np.ones((3, 3))
    seeds = [_rows("v", alphas, ones * s, [2.0 * s, 3.0 * s, 4.0 * s]) for s in (1.0, 3.0)]
    mean = pp.mean_over_seeds(seeds, "v", "variant")
    assert list(mean["nrmse"]) == [4.0, 6.0, 8.0] and list(mean["seeds"]) == [2, 2, 2]
    ekf = _rows("ekf", alphas, ones, [1.0, 5.0, 9.0])
    fit = _rows(pp.PAPER_FIT, alphas, ones, [1.0, 7.0, 12.0])
    table = pd.concat([mean, ekf, fit], ignore_index=True)
    out = pp.variant_summary(table, pd.DataFrame([{"label": "variant", "model": "cnn"}]))
    row = out.iloc[0]
    assert row["x_3"] == pytest.approx(2.0) and row["psi_6"] == pytest.approx(2000.0)
    assert row["growth"] == pytest.approx(2.0)
    assert row["spread_6"] == pytest.approx((12.0 - 4.0) / 8.0)
    # below the EKF only at alpha 6: crosses between 3 and 6 (6 - 5 = 1 above, 8 - 9 = -1 below)
    assert row["crossover_ekf"] == pytest.approx(4.5)
    assert row["crossover_ekf_paper_fit"] == pytest.approx(1.0 + 2.0 * 3.0 / 4.0)


@pytest.mark.slow
def test_ablation_command_at_smoke_size(tmp_path, smoke_data, tracking, one_torch_thread,
                                        capsys):
    """The command end to end, its store given as ``tracking_uri=`` (not the environment's:
    the runs log where the tables are read from)."""
    from hydra import compose, initialize_config_dir

    from lbo.ablation import ablation
    from lbo.core.paths import CONF_DIR

    sweep = ("model=cnn window=20 features=relative,frame trainer.max_epochs=1 "
             "trainer.limit_train_batches=3")
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("ablation", ["scale=smoke", f"sweeps=['{sweep}']",
                                   f"overrides=['data.root={smoke_data.parent}']",
                                   f"report_dir={tmp_path / 'abl'}",
                                   f"tracking_uri=sqlite:///{tmp_path / 'given.db'}"])
        out = ablation(cfg)
    printed = capsys.readouterr().out
    # the time it will take, measured, before the first run trains; an ETA after the first
    estimate = re.search(r"expected: about (\d+) s of training at scale smoke", printed)
    assert estimate and printed.index("expected: about") < printed.index("==> [1/2]")
    # each run timed, or, once timing costs about what training does (eta.plan), the rest
    # expected to take as long as those timed, in a line
    timed = len(re.findall(r"cnn-N20 \w+ .*seed \d+: \d+ steps x [\d.]+ ms", printed))
    rest = re.search(r"the other (\d+): about \d+ s each, as the (\d+) measured", printed)
    assert timed >= 1 and timed + (int(rest[1]) if rest else 0) == 2
    assert rest is None or int(rest[2]) == timed
    assert re.search(r"trained in \d+ s: MLflow run \w+, ETA", printed)
    assert (tmp_path / "given.db").is_file() and not (tmp_path / "mlflow.db").exists()
    for name in ("ekf_fit.csv", "scores.csv", "ablation.csv", "ablation.md", "ablation.png"):
        assert (out / name).stat().st_size > 100, name
    summary = pd.read_csv(out / "ablation.csv")
    # one epoch against the smoke experiment's two: the label says so
    assert list(summary["label"]) == ["cnn-N20 relative fresh centred_sigmoid standard 1 epoch",
                                      "cnn-N20 frame fresh centred_sigmoid standard 1 epoch"]
    assert summary[["x_1", "psi_6", "growth", "paper_alpha6"]].notna().all().all()
    scores = pd.read_csv(out / "scores.csv")
    assert {"ekf", "oracle", pp.PAPER_FIT, "paper_cnn"} <= set(scores["observer"])
    md = (out / "ablation.md").read_text()
    assert "The paper's EKF" in md and "Closest setting" in md
