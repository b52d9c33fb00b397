"""`lbo.simulate manoeuvre=free_drive` and `drives=N`: a fleet of varied training drives."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from helpers import cli, compose_cfg
from lbo.core.angles import wrap_angle
from lbo.core.errors import LboError
from lbo.sim import columns
from lbo.simulate import simulate, write_logs

FREE = ["manoeuvre=free_drive", "duration=10"]


def free(*overrides: str) -> pd.DataFrame:
    return simulate(compose_cfg("simulate", [*FREE, *overrides]))


def yaw_residual(df: pd.DataFrame, wheelbase: float, dt: float) -> float:
    """RMS (rad/s) of the yaw rate the kinematic bicycle does not explain."""
    kinematic = (df["V"] * np.tan(df["delta"]) / wheelbase).to_numpy()[:-1]
    return float(np.sqrt(np.mean((wrap_angle(np.diff(df["psi"].to_numpy())) / dt
                                  - kinematic) ** 2)))


def test_free_drive_is_one_seeded_friction_circle_trajectory():
    cfg = compose_cfg("simulate", FREE)
    assert cfg.vehicle.dt == 0.02
    df = simulate(cfg)
    assert tuple(df.columns) == columns.SCORED_SET  # the columns of the other logs
    assert len(df) == 500
    assert np.isfinite(df.drop(columns="scored").to_numpy(float)).all()
    np.testing.assert_array_equal(df["k"], np.arange(500))
    assert (df["traj"] == 0).all() and df["scored"].all() and (df["alpha"] == 1.0).all()
    assert df["V"].std() > 0.5 and df["V"].max() - df["V"].min() > 2.0  # varied speeds
    assert df["delta"].abs().max() > 0.01  # and it turns
    again = free()
    pd.testing.assert_frame_equal(df, again)
    assert df.to_csv(index=False) == again.to_csv(index=False)  # byte-identical logs
    other = free("seed=1")
    assert not np.allclose(df[["x", "y", "V"]], other[["x", "y", "V"]])


def test_free_drive_thins_fixes_and_scales_the_noise():
    df = free("fix_rate=10", "alpha=2")
    fix = df[["x_m", "y_m", "psi_m"]].notna().all(axis=1).to_numpy()
    assert fix.sum() == 100 and fix[::5].all()
    assert df[["x_m", "y_m", "psi_m"]].notna().any(axis=1).sum() == 100  # all or nothing
    assert (df["alpha"] == 2.0).all()


def test_dynamic_truth_gives_a_car_that_slips():
    dynamic_cfg = compose_cfg("simulate", [*FREE, "data=dynamic"])
    kinematic_cfg = compose_cfg("simulate", [*FREE, "data=dynamic", "car=kinematic"])
    assert dynamic_cfg.car.name == "dynamic" and kinematic_cfg.car.name == "kinematic"
    dyn, kin = simulate(dynamic_cfg), simulate(kinematic_cfg)
    assert len(dyn) == len(kin) == 500 and np.isfinite(dyn.drop(columns="scored")).all().all()
    assert not np.allclose(dyn[["x", "y", "psi"]], kin[["x", "y", "psi"]])
    v = dynamic_cfg.vehicle
    # the kinematic truth leaves only process noise; the dynamic car's yaw rate slips from it
    assert yaw_residual(dyn, v.wheelbase, v.dt) > 1.2 * yaw_residual(kin, v.wheelbase, v.dt)


def test_drives_write_a_fleet_of_seeded_logs(tmp_path):
    out = tmp_path / "fleet" / "train" / "drive.csv"  # the folder does not exist yet
    res = cli("lbo.simulate", *FREE, "duration=4", "drives=3", "seed=5", f"output={out}",
              f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    names = ["drive_000.csv", "drive_001.csv", "drive_002.csv"]
    assert sorted(p.name for p in out.parent.iterdir()) == names
    lines = res.stdout.strip().splitlines()
    assert len(lines) == 4
    for line, name in zip(lines, names):
        assert line.startswith("free_drive: 200 rows") and line.endswith(str(out.parent / name))
    assert lines[-1].startswith("simulated 3 drives")
    texts = [(out.parent / n).read_bytes() for n in names]
    assert len(set(texts)) == 3
    logs = [pd.read_csv(out.parent / n) for n in names]
    assert all(len(d) == 200 for d in logs)
    single = tmp_path / "single.csv"
    write_logs(compose_cfg("simulate", [*FREE, "duration=4", "seed=6", f"output={single}"]))
    assert single.read_bytes() == texts[1]


def test_one_drive_writes_output_itself(tmp_path, capsys):
    out = tmp_path / "log.parquet"
    assert write_logs(compose_cfg("simulate", [*FREE, "duration=2", f"output={out}"])) == out
    assert [p.name for p in tmp_path.iterdir()] == ["log.parquet"]
    assert capsys.readouterr().out.strip().splitlines()[-1] == f"simulated: {out}"
    assert len(pd.read_parquet(out)) == 100


@pytest.mark.parametrize(("override", "field"), [
    ("duration=0", "duration"), ("duration=-1", "duration"), ("duration=x", "duration"),
    ("duration=0.01", "duration"), ("drives=0", "drives"), ("drives=1.5", "drives"),
    ("drives=x", "drives"),
])
def test_bad_duration_or_drives_is_one_line_and_writes_nothing(tmp_path, override, field):
    cfg = compose_cfg("simulate", [*FREE, "drives=3", override,
                                   f"output={tmp_path / 'fleet' / 'drive.csv'}"])
    with pytest.raises(LboError) as err:
        write_logs(cfg)
    message = str(err.value)
    assert message.startswith(f"{field} must be ") and "\n" not in message
    assert list(tmp_path.iterdir()) == []
