"""Why the car-that-slips observer's covariance is honest with white noise but not with drift.

    python benchmarks/drift_calibration.py --run <output dir of
        `lbo.train experiment=dynamic_carried data=dynamic_drift`> [--alphas 0.25 1 3 6]

Runs the run's recursive form (``checkpoints/best.ckpt``, its data set found under ``data/`` by
the data hash in the checkpoint) over the test grid at the given alpha levels and prints, per
level, over the scored points:

- ``R sigma``: the noise model's white position sigma (the root of the mean of R's x and y
  variances), and ``true``: the data's (``noise.measurement_sigma`` times alpha);
- ``drift sigma``: the drift states' stationary sigma the filter gives itself (its learned
  ratio times R's white sigma), and ``true``: the data's (``sensors.gnss_sigma`` times alpha);
- ``NEES xy`` (2 for an honest filter) and ``NEES psi`` (1): the position's and the heading's
  shares of the mean NEES;
- ``err/P xy``: the mean square position error over the mean of the position variances P
  reports (1 for an honest filter).

Its header gives the drift's correlation time and size the filter learned beside the data's.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch
from dynamic_segments import run_and_data

from lbo.core.angles import wrap_angle
from lbo.core.paths import REPO_ROOT
from lbo.models.recursive import RecursiveFilter
from lbo.scoring.grid import load_test
from lbo.sim.truth import of_folder


class Recorded(RecursiveFilter):
    """The recursive form, keeping each step's R (B, 3, 3) and drift variance (B,)."""

    def __init__(self, net) -> None:
        super().__init__(net)
        self.R: list[torch.Tensor] = []
        self.var_b: list[torch.Tensor] = []

    def _noise(self, sums, speed, heading):
        R = super()._noise(sums, speed, heading)
        self.R.append(R)
        return R

    def _drift_variance(self, R):
        var_b = super()._drift_variance(R)
        if len(self.var_b) < len(self.R):  # once a step (the start asks again)
            self.var_b.append(var_b)
        return var_b


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, type=Path, help="output dir of the training run")
    p.add_argument("--alphas", type=float, nargs="+", default=[0.25, 0.5, 1.0, 2.0, 3.0, 4.0,
                                                                5.0, 6.0])
    p.add_argument("--data-root", type=Path, default=REPO_ROOT / "data")
    args = p.parse_args()
    net, _, vehicle, noise, folder = run_and_data(args.run, args.data_root)
    truth = of_folder(folder, vehicle.wheelbase)
    arr = load_test(folder / "test.parquet")
    sigma, drift = float(noise.measurement_sigma[0]), truth.sensors.gnss_sigma
    print(f"{folder.name}: white sigma {sigma} m, drift sigma {drift} m at alpha = 1 "
          f"(correlation time {truth.sensors.gnss_tau} s)")
    fo = net.net
    if fo.drift:  # what the filter learned of the drift, beside the data's
        tau, ratio = fo.log_drift_tau.item(), fo.log_drift_ratio.item()
        print(f"learned: correlation time {math.exp(tau) * fo.dt:.2f} s, drift sigma "
              f"{math.exp(ratio):.3f} of the white sigma (data: {drift / sigma:.3f})")
    print(f"{'alpha':>5} {'R sigma':>8} {'true':>6} {'drift sigma':>11} {'true':>6} "
          f"{'NEES xy':>8} {'NEES psi':>8} {'err/P xy':>8}")
    for alpha in args.alphas:
        level = np.isclose(arr.alpha, alpha)
        m, u, z, mask = arr.m[level], arr.u[level], arr.z[level], arr.mask[level]
        rec = Recorded(net.net)
        mt, ut = (torch.from_numpy(np.require(x, requirements="W")) for x in (m, u))
        with torch.inference_mode():
            est, cov = (t.numpy() for t in rec.run(mt, ut)[:2])
        R = torch.stack(rec.R, 1).numpy()[mask]  # (points, 3, 3)
        var_b = torch.stack(rec.var_b, 1).numpy()[mask] if rec.var_b else np.zeros(len(R))
        err = est - z
        err[..., 2] = wrap_angle(err[..., 2])
        e, P = err[mask], cov[mask]
        nees_xy = np.einsum("ni,nij,nj->n", e[:, :2], np.linalg.inv(P[:, :2, :2]), e[:, :2])
        nees_psi = e[:, 2] ** 2 / P[:, 2, 2]
        r_sigma = np.sqrt(np.mean((R[:, 0, 0] + R[:, 1, 1]) / 2))
        ratio = np.mean(e[:, 0] ** 2 + e[:, 1] ** 2) / np.mean(P[:, 0, 0] + P[:, 1, 1])
        print(f"{alpha:5.2f} {r_sigma:8.3f} {sigma * alpha:6.3f} {np.sqrt(var_b.mean()):11.3f} "
              f"{drift * alpha:6.3f} {nees_xy.mean():8.2f} {nees_psi.mean():8.2f} "
              f"{ratio:8.2f}", flush=True)


if __name__ == "__main__":
    main()
