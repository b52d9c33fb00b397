"""What the RTS smoother gains over filtering on an offline log: a stop-and-go drive.

    python benchmarks/smoothing.py [--robust <checkpoint | run id>] [--seeds 3]

For alpha 1, 3 and 6, a simulated stop-and-go log (``lbo.simulate manoeuvre=stop_and_go``:
standstill, starts from rest, creeping; fixes at every step) is observed by each classical
filter and, given ``--robust``, the robust observer, once filtered and once smoothed
(``Observer.run(..., smooth=True)``, as ``lbo.observe smooth=true`` does). The table gives the
RMSE of x, y (m) and psi (mrad) of each, pooled over ``--seeds`` drives, and the smoother's
gain in position RMSE. The test grid's gains come from ``python -m lbo.evaluate data=robust
smooth=true``.
"""

from __future__ import annotations

import argparse

import numpy as np

from lbo.serve.observer import Observer
from lbo.simulate import simulate

ALPHAS = (1.0, 3.0, 6.0)


def drives(alpha: float, seeds: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``seeds`` stop-and-go logs at ``alpha``: (m (T, 3), u (T, 2), z (T, 3)) each."""
    from hydra import compose, initialize_config_dir

    from lbo.core.paths import CONF_DIR

    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("simulate", ["manoeuvre=stop_and_go", f"alpha={alpha}"])
    out = []
    for seed in range(seeds):
        df = simulate(cfg, seed=seed)
        out.append((df[["x_m", "y_m", "psi_m"]].to_numpy(), df[["V", "delta"]].to_numpy(),
                    df[["x", "y", "psi"]].to_numpy()))
    return out


def rmse(est: list[np.ndarray], truth: list[np.ndarray]) -> np.ndarray:
    e = np.concatenate([a - b for a, b in zip(est, truth)])
    e[:, 2] = (e[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return np.sqrt(np.nanmean(e**2, axis=0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robust", help="the robust observer: a checkpoint or MLflow run id")
    parser.add_argument("--seeds", type=int, default=3)
    args = parser.parse_args()
    print(f"RMSE on stop-and-go logs ({args.seeds} drives per alpha): filtered -> smoothed, "
          "x (m), y (m), psi (mrad)")
    print()
    print("| alpha | observer | filtered | smoothed | position gain |")
    print("|---|---|---|---|---|")
    for alpha in ALPHAS:
        logs = drives(alpha, args.seeds)
        observers = [Observer.load(n, alpha=alpha) for n in ("ekf", "oracle", "adaptive", "ukf")]
        if args.robust:
            observers.append(Observer.load(args.robust))
        for obs in observers:
            runs = {s: [obs.run(m, u, smooth=s)[0] for m, u, _ in logs] for s in (False, True)}
            truth = [z for _, _, z in logs]
            f, s = rmse(runs[False], truth), rmse(runs[True], truth)
            gain = 1 - np.hypot(*s[:2]) / np.hypot(*f[:2])
            cells = [f"{v[0]:.3f}, {v[1]:.3f}, {1e3 * v[2]:.2f}" for v in (f, s)]
            print(f"| {alpha:g} | {obs.name} | {cells[0]} | {cells[1]} | {gain:.0%} |",
                  flush=True)


if __name__ == "__main__":
    main()
