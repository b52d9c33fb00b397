from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from helpers import cli, compose_cfg
from lbo.core.errors import LboError
from lbo.datagen import generate
from lbo.sim import columns, schema
from lbo.sim.datasets import G, build, make_test, spec_from_cfg
from lbo.sim.friction import Grid, accelerations, generate_train
from lbo.sim.manoeuvres import MANOEUVRES
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle


def smoke_spec(root, *overrides):
    return spec_from_cfg(compose_cfg("datagen", ["data=smoke", f"data.root={root}", *overrides]))


def test_sets_follow_the_schema(smoke_data):
    train = pd.read_parquet(smoke_data / "train.parquet")
    assert tuple(train.columns) == columns.SET
    for name in ("val", "test"):
        df = pd.read_parquet(smoke_data / f"{name}.parquet")
        assert tuple(df.columns) == columns.SCORED_SET
        assert df["scored"].dtype == bool
    assert (smoke_data / "friction_circle.png").stat().st_size > 10_000
    assert (smoke_data / "test_manoeuvres.png").stat().st_size > 10_000


def test_validation_set_is_the_clothoid_sinusoid(smoke_data):
    val = pd.read_parquet(smoke_data / "val.parquet")
    scored = val[val["scored"]]
    assert len(scored) == 995 and (val["alpha"] == 1.0).all()
    assert scored["k"].min() >= 80
    assert scored["x"].min() < 5 and 190 < scored["x"].max() < 215
    assert 4.0 < scored["y"].max() < 6.5 and -6.5 < scored["y"].min() < -4.0
    assert scored["V"].std() > 0.3  # the speed varies


def test_test_set_levels_share_truth_but_not_noise(smoke_data):
    test = pd.read_parquet(smoke_data / "test.parquet")
    alphas = np.sort(test["alpha"].unique())
    np.testing.assert_allclose(alphas, np.arange(7.0))
    by = {a: g.sort_values(["traj", "k"]).reset_index(drop=True) for a, g in test.groupby("alpha")}
    for col in ("x", "y", "psi", "V", "delta"):
        np.testing.assert_array_equal(by[1.0][col], by[6.0][col])
    np.testing.assert_array_equal(by[0.0]["x_m"], by[0.0]["x"])  # alpha=0: exact measurements
    e1 = (by[1.0]["x_m"] - by[1.0]["x"]).to_numpy()
    e6 = (by[6.0]["x_m"] - by[6.0]["x"]).to_numpy()
    assert abs(np.corrcoef(e1, e6)[0, 1]) < 0.1  # independent noise per level
    np.testing.assert_allclose(e6.std() / e1.std(), 6.0, rtol=0.1)


def test_every_manoeuvre_has_a_run_in_and_its_scored_steps(smoke_data):
    test = pd.read_parquet(smoke_data / "test.parquet")
    one = test[test["alpha"] == 1.0]
    names = ["double_lane_change", "hairpin", "braking_in_bend"]
    for i, name in enumerate(names):
        g = one[one["traj"] == i]
        assert g.loc[~g["scored"], "k"].max() + 1 >= 80
        assert g["scored"].sum() == MANOEUVRES[name].steps
        assert (g.loc[g["scored"], "k"].min()) == 100


def test_paper_test_grid_has_9829_points_at_25_levels(tmp_path):
    spec = spec_from_cfg(compose_cfg("datagen", ["data=paper", f"data.root={tmp_path}"]))
    test = make_test(spec)
    assert len(spec.alphas) == 25 and spec.alphas[-1] == 6.0
    assert int(test["scored"].sum()) == 245_725
    assert test.groupby("alpha")["scored"].sum().eq(9_829).all()
    # pure pursuit keeps to the path: no manoeuvre wanders off
    arr = schema.to_arrays(test[test["alpha"] == 0.0])
    assert np.abs(arr.u[..., 1]).max() <= Vehicle().delta_max + 1e-12


def test_training_fills_the_friction_circle_within_the_limits():
    v = Vehicle()
    out = generate_train(200, 2000, v, Noise.preset("paper"), np.random.default_rng(0))
    V, delta = out["u"][..., 0], out["u"][..., 1]
    assert V.min() >= v.v_min and V.max() <= v.v_max
    assert np.abs(delta).max() <= v.delta_max + 1e-12
    acc = accelerations(V, delta, v.dt, v.wheelbase).reshape(-1, 2)
    grid = Grid(0.5 * G, 20)
    assert grid.coverage(acc) >= 0.9
    assert np.mean(np.hypot(*acc.T) <= 0.5 * G * 1.05) > 0.99
    counts = grid.counts(acc)[grid.inside]
    assert counts.min() > 0.5 * np.median(counts)  # evenly, not just touched
    np.testing.assert_allclose(out["z"][:, 0, :2], 0.0)
    psi0 = out["z"][:, 0, 2]
    assert psi0.min() < -2.5 and psi0.max() > 2.5


def test_same_seed_same_bytes_other_seed_other_data(tmp_path):
    a, _, _ = build(smoke_spec(tmp_path / "a"), progress=False)
    b, _, _ = build(smoke_spec(tmp_path / "b"), progress=False)
    c, _, _ = build(smoke_spec(tmp_path / "c", "data.seed=1"), progress=False)
    for name in ("train", "val", "test"):
        assert (a / f"{name}.parquet").read_bytes() == (b / f"{name}.parquet").read_bytes()
        pd.testing.assert_frame_equal(pd.read_parquet(a / f"{name}.parquet"),
                                      pd.read_parquet(b / f"{name}.parquet"))
        assert not pd.read_parquet(a / f"{name}.parquet").equals(
            pd.read_parquet(c / f"{name}.parquet"))
    assert a.name == b.name != c.name


def test_cache_is_reused_and_keyed_by_config(tmp_path):
    spec = smoke_spec(tmp_path)
    folder, _, cached = build(spec, progress=False)
    assert not cached
    (folder / ".train.parquet.abc.tmp").write_bytes(b"half")  # a killed writer's leftover
    mtime = (folder / "train.parquet").stat().st_mtime_ns
    again, _, cached = build(spec, progress=False)
    assert cached and again == folder and (folder / "train.parquet").stat().st_mtime_ns == mtime
    other = smoke_spec(tmp_path, "vehicle.wheelbase=3.0")
    assert other.folder != folder


def test_a_missing_set_is_regenerated_alone(tmp_path):
    spec = smoke_spec(tmp_path)
    folder, _, _ = build(spec, progress=False)
    before = (folder / "test.parquet").read_bytes()
    (folder / "test.parquet").unlink()
    _, _, cached = build(spec, progress=False)
    assert not cached and (folder / "test.parquet").read_bytes() == before


@pytest.mark.parametrize("override, field", [
    ("vehicle.dt=0", "vehicle.dt"),
    ("vehicle.dt=-0.02", "vehicle.dt"),
    ("noise.measurement_sigma=[1.0,-1.0,0.01]", "noise.measurement_sigma"),
    ("noise.process_sigma=[-0.1,0.1,0.01]", "noise.process_sigma"),
    ("data.train.radius_g=0", "data.train.radius_g"),
    ("data.train.n_traj=0", "data.train.n_traj"),
    ("data.test.manoeuvres=[slalom,moonwalk]", "data.test.manoeuvres"),
    ("data.test.run_in=50", "data.test.run_in"),
    ("data.test.alpha_step=0", "data.test.alpha_step"),
    ("data.train.hold=[2.0,1.0]", "data.train.hold"),
])
def test_bad_config_names_the_field_and_writes_nothing(tmp_path, override, field):
    cfg = compose_cfg("datagen", ["data=smoke", f"data.root={tmp_path / 'data'}", override])
    with pytest.raises(LboError, match=field.replace(".", r"\.")) as err:
        generate(cfg)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "data").exists()


def test_cli_prints_the_folder_and_refuses_bad_input(tmp_path):
    root = tmp_path / "data"
    ok = cli("lbo.datagen", "data=smoke", f"data.root={root}", f"hydra.run.dir={tmp_path / 'run'}")
    assert ok.returncode == 0, ok.stderr[-3000:]
    last = ok.stdout.strip().splitlines()[-1]
    assert last.startswith("datasets: ")
    folder = Path(last.removeprefix("datasets: "))
    assert sorted(p.name for p in folder.glob("*.parquet")) == [
        "test.parquet", "train.parquet", "val.parquet"]
    assert "coverage" in ok.stdout
    bad = cli("lbo.datagen", "data=smoke", f"data.root={tmp_path / 'bad'}",
              "data.train.n_traj=0", f"hydra.run.dir={tmp_path / 'run2'}")
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines()[-1].startswith("error: data.train.n_traj must be")
    assert not (tmp_path / "bad").exists()


def test_reading_a_set_checks_its_columns(tmp_path):
    df = pd.DataFrame({"traj": [0], "k": [0], "t": [0.0], "x": [0.0]})
    schema.write_set(df, tmp_path / "x.parquet")
    with pytest.raises(LboError, match="missing column 'y'"):
        schema.read_set(tmp_path / "x.parquet")
    with pytest.raises(LboError, match="not found"):
        schema.read_set(tmp_path / "nope.parquet")
    full = {c: [0.0, np.nan] for c in columns.SET}
    schema.write_set(pd.DataFrame(full), tmp_path / "nan.parquet")
    with pytest.raises(LboError, match="column 'traj' has NaN"):
        schema.read_set(tmp_path / "nan.parquet")
