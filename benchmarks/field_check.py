"""A learned observer on simulated logs like a real car's: standstill and slow position fixes.

    python benchmarks/field_check.py --observer <checkpoint | run id> [--seeds 3]

Conditions (inputs at 50 Hz, the vehicle's dt): the stop-and-go drive (standing still 32% of
the time) and the 15 test manoeuvres, with a fix at every step, at 10 Hz and at 1 Hz, at
alpha = 1 and 3, plus alpha = 0.5 and 5 as off-grid noise levels. Every log comes from
``lbo.simulate`` (seeds 0 .. seeds-1). For each condition the RMSE per variable is pooled
over every row from the first fix on, for the observer, the oracle EKF (told alpha,
prediction-only steps between fixes) and the paper's EKF (R at alpha = 1). The table gives
the ratios observer / oracle and observer / EKF, per variable, and the worst of each.
"""

from __future__ import annotations

import argparse

import numpy as np
from hydra import compose, initialize_config_dir

from lbo.core.angles import wrap_angle
from lbo.core.paths import CONF_DIR
from lbo.serve.observer import Observer
from lbo.sim.manoeuvres import MANOEUVRES
from lbo.simulate import STOP_AND_GO, simulate

RATES = (None, 10.0, 1.0)
ALPHAS = (1.0, 3.0, 0.5, 5.0)


def errors(obs: Observer, df) -> np.ndarray:
    """(R, 3) errors of ``obs`` on the log's rows from its first fix on."""
    m = df[["x_m", "y_m", "psi_m"]].to_numpy(float)
    u = df[["V", "delta"]].to_numpy(float)
    z = df[["x", "y", "psi"]].to_numpy(float)
    est, valid = obs.run(m, u)
    first = int(np.argmax(np.isfinite(m).all(1)))
    if not valid[first:].all():
        raise SystemExit(f"{obs.name}: invalid rows after the first fix")
    e = est[first:] - z[first:]
    e[:, 2] = wrap_angle(e[:, 2])
    return e


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--observer", required=True)
    p.add_argument("--seeds", type=int, default=3)
    args = p.parse_args()
    learned = Observer.load(args.observer)
    print(f"{learned!r}; pooled RMSE ratios over {args.seeds} seeds")
    print(f"{'log':13s} {'fixes':>6s} {'alpha':>5s} | {'vs oracle: x':>12s} {'y':>5s} "
          f"{'psi':>5s} | {'vs EKF: x':>9s} {'y':>5s} {'psi':>5s}")
    worst = {"oracle": 0.0, "ekf": 0.0}
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        for alpha in ALPHAS:
            for rate in RATES:
                for logs in ([STOP_AND_GO], list(MANOEUVRES)):
                    err = {"learned": [], "oracle": [], "ekf": []}
                    for seed in range(args.seeds):
                        for name in logs:
                            cfg = compose("simulate", [f"manoeuvre={name}", f"alpha={alpha}",
                                                       f"fix_rate={rate or 'null'}",
                                                       f"seed={seed}"])
                            df = simulate(cfg)
                            err["learned"].append(errors(learned, df))
                            err["oracle"].append(errors(Observer("oracle", alpha=alpha), df))
                            err["ekf"].append(errors(Observer("ekf"), df))
                    rmse = {k: np.sqrt(np.mean(np.concatenate(v) ** 2, axis=0))
                            for k, v in err.items()}
                    r_o = rmse["learned"] / rmse["oracle"]
                    r_e = rmse["learned"] / rmse["ekf"]
                    worst["oracle"] = max(worst["oracle"], r_o.max()) if alpha in (1, 3) \
                        else worst["oracle"]
                    worst["ekf"] = max(worst["ekf"], r_e.max())
                    label = "stop_and_go" if len(logs) == 1 else "15 manoeuvres"
                    print(f"{label:13s} {(f'{rate:g} Hz' if rate else '50 Hz'):>6s} "
                          f"{alpha:5g} | {r_o[0]:12.3f} {r_o[1]:5.3f} {r_o[2]:5.3f} | "
                          f"{r_e[0]:9.3f} {r_e[1]:5.3f} {r_e[2]:5.3f}", flush=True)
    print(f"worst ratio to the oracle EKF at alpha 1 and 3: {worst['oracle']:.3f}")
    print(f"worst ratio to the EKF, every condition: {worst['ekf']:.3f}")


if __name__ == "__main__":
    main()
