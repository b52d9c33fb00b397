"""Leave-one-drive-out on the hill drive, the gyro EKF's noise learned by the innovations on
training drives whose fixes are thinned: one fix kept every ``every_s`` seconds, the others
blanked (``positions``: the position only, the course kept at every fix; ``receiver``: every
receiver column). No truth is read in any fit; the drive left out is scored with all its fixes.

Why: a receiver's slow errors make consecutive fixes' errors alike, and the likelihood of a
filter that takes them as white rewards following them. Fixes far enough apart have errors
that are nearly independent, and their innovations judge the receiver by its whole error.

    python benchmarks/thinned_fixes.py 10 positions     # about 4 min on a 2-core CPU
"""

import sys
import time

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from lbo.learn import gyro_fit
from lbo.learn.gyro_fit import Settings
from lbo.logs import hguide
from lbo.scoring import drives as across
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

every_s = float(sys.argv[1]) if len(sys.argv) > 1 else 10.0
which = sys.argv[2] if len(sys.argv) > 2 else "positions"
extra = sys.argv[3:]  # learn.* overrides, e.g. learn.drift=true
COLUMNS = {"positions": ["x_m", "y_m", "sx_m", "sy_m"],
           "receiver": ["x_m", "y_m", "sx_m", "sy_m", "ve_m", "vn_m", "sv_m"]}[which]
cfg = OmegaConf.merge(OmegaConf.load("conf/realdrive.yaml"), OmegaConf.from_dotlist(extra))
cfg.learn.objective = "innovations"
vehicle = Vehicle()
noise = Noise.from_cfg(OmegaConf.load("conf/noise/paper.yaml"))  # lbo.realdrive's default
drives = hguide.drives(hguide.to_log(hguide.read(), vehicle))  # its alignment fitted
settings = Settings.from_cfg(cfg.learn)
R, start = gyro_fit.fix_cov(noise), settings.start(noise.Q)


def thinned(drive: pd.DataFrame) -> pd.DataFrame:
    """``drive`` with one fix kept every ``every_s`` s, ``COLUMNS`` blanked at the others."""
    fixes = np.flatnonzero(np.isfinite(drive["x_m"].to_numpy(float)))
    t = drive["t"].to_numpy(float)[fixes]
    kept = fixes[np.r_[True, np.diff(np.floor((t - t[0]) / every_s)) > 0]]
    out = drive.copy()
    blank = np.setdiff1d(fixes, kept)
    out.loc[out.index[blank], COLUMNS] = np.nan
    return out.drop(columns=["x", "y", "psi"])  # no truth in the fit


def learn(k: int, train: list[pd.DataFrame]) -> across.Fold:
    begin = time.perf_counter()
    logs = [thinned(d) for d in train]
    fitted = gyro_fit.fit(logs, logs, vehicle, R, start, progress=None,
                          **settings.kwargs(vehicle.dt))
    print(f"drive {k + 1} left out: {time.perf_counter() - begin:.0f} s, epoch "
          f"{fitted.best_epoch}, {fitted.noise}", flush=True)
    return across.Fold({f"gyro, innovations of a fix every {every_s:g} s ({which})":
                        fitted.noise}, {})


table = across.leave_one_out(drives, learn, ["ekf", "gyro"], vehicle, noise)
print(across.markdown(across.summary(table)), end="")
