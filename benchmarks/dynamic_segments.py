"""Where learning beats the model, and where it does not: a car-that-slips observer by segment.

    python benchmarks/dynamic_segments.py --run <output dir of `lbo.train experiment=dynamic`>

Reads the run's checkpoint (``checkpoints/best.ckpt``) and its data set (found by the data
hash in the checkpoint, under ``data/``), runs it, the kinematic oracle EKF and the EKF told
the car (``oracle_dynamic``) on the test grid at the given alpha levels, and prints the RMSE
of position (x and y pooled, m) and heading (mrad) over the scored points of four segments:
straights (kinematic yaw rate below 0.05 rad/s), corners (above 0.2 rad/s), low speed
(V < 5 m/s) and higher speed (V > 8 m/s).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from lbo.core.angles import wrap_angle
from lbo.core.paths import REPO_ROOT
from lbo.models.checkpoint import read_checkpoint, trained_conditions
from lbo.scoring.grid import classical, load_test, predict_grid
from lbo.sim.noise import Noise
from lbo.sim.truth import of_folder
from lbo.sim.vehicle import Vehicle


def segments(arr: dict[str, np.ndarray], wheelbase: float) -> dict[str, np.ndarray]:
    """(G, T) masks of the four segments."""
    v, delta = arr["u"][..., 0], arr["u"][..., 1]
    r_kin = np.abs(v * np.tan(delta) / wheelbase)
    return {"straight": r_kin < 0.05, "corner": r_kin > 0.2, "V < 5 m/s": v < 5.0,
            "V > 8 m/s": v > 8.0}


def run_and_data(run: Path, data_root: Path) -> tuple[Any, dict[str, Any], Vehicle, Noise, Path]:
    """A training run's observer (``run/checkpoints/best.ckpt``), its hyperparameters, the
    vehicle and noise it was trained with, and its data-set folder, found under ``data_root``
    by the data hash its checkpoint records."""
    net, hp = read_checkpoint(run / "checkpoints" / "best.ckpt")
    vehicle, noise = trained_conditions(hp, str(run))
    found = sorted(data_root.glob(f"*-{hp['meta']['data_hash']}"))
    if not found:
        raise SystemExit(f"no data set {hp['meta']['data_hash']} under {data_root}")
    return net, hp, vehicle, noise, found[0]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, type=Path, help="output dir of the training run")
    p.add_argument("--alphas", type=float, nargs="+", default=[1.0, 3.0])
    p.add_argument("--data-root", type=Path, default=REPO_ROOT / "data")
    args = p.parse_args()
    net, hp, vehicle, noise, folder = run_and_data(args.run, args.data_root)
    truth = of_folder(folder, vehicle.wheelbase)
    arr = load_test(folder / "test.parquet")
    pick = np.isin(np.round(arr["alpha"], 9), args.alphas)
    arr = {k: v[pick] if isinstance(v, np.ndarray) and v.shape[:1] == pick.shape else v
           for k, v in arr.items()}
    name = f"{hp['model']['name']}-N{hp['window']}"
    est = {name: predict_grid(net, arr, hp["window"]),
           "oracle": classical("oracle", arr, vehicle, noise),
           "oracle_dynamic": classical("oracle_dynamic", arr, vehicle, noise, truth=truth)}
    masks = segments(arr, vehicle.wheelbase)
    print(f"{folder.name}: RMSE of position (m) / heading (mrad) by segment")
    print(f"{'alpha':>5} {'segment':>10} {'points':>7} " + " ".join(f"{k:>22}" for k in est))
    for alpha in args.alphas:
        level = np.isclose(arr["alpha"], alpha)[:, None]
        for seg, m in masks.items():
            mask = arr["mask"] & m & level
            cells = []
            for e in est.values():
                err = e - arr["z"]
                err[..., 2] = wrap_angle(err[..., 2])
                pos = np.sqrt(np.mean(err[mask][:, :2] ** 2))
                psi = 1e3 * np.sqrt(np.mean(err[mask][:, 2] ** 2))
                cells.append(f"{pos:10.3f} / {psi:9.1f}")
            print(f"{alpha:5g} {seg:>10} {int(mask.sum()):7d} " + " ".join(f"{c:>22}"
                                                                          for c in cells))


if __name__ == "__main__":
    main()
