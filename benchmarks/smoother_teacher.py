"""Leave-one-drive-out on the hill drive, the gyro EKF's noise learned against a smoother's
poses instead of the truth: no truth read in any fit (the truth only scores). Each training
drive's x, y and psi are replaced by the RTS smoother of ``teacher`` (``ekf`` or ``ukf``: the
classical observers that smooth) run on the drive's receiver channels; the fit is
``lbo.realdrive``'s (``conf/realdrive.yaml``'s ``learn``, objective ``truth``) on them.

    python benchmarks/smoother_teacher.py [ekf|ukf]     # about 6 min on a 2-core CPU
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
from lbo.scoring.receiver import STATE, receiver
from lbo.serve.observer import Observer
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

teacher = sys.argv[1] if len(sys.argv) > 1 else "ekf"
cfg = OmegaConf.load("conf/realdrive.yaml")
vehicle = Vehicle()
noise = Noise.from_cfg(OmegaConf.load("conf/noise/paper.yaml"))  # lbo.realdrive's default
drives = hguide.drives(hguide.to_log(hguide.read(), vehicle))  # its alignment fitted
settings = Settings.from_cfg(cfg.learn)
R, start = gyro_fit.fix_cov(noise), settings.start(noise.Q)


def taught(drive: pd.DataFrame) -> pd.DataFrame:
    """``drive`` with its truth replaced by the teacher's smoothed poses (NaN where none)."""
    m, u = drive[["x_m", "y_m", "psi_m"]].to_numpy(float), drive[["V", "delta"]].to_numpy(float)
    est, valid = Observer.load(teacher, vehicle, noise).run(m, u, receiver=receiver(drive),
                                                             smooth=True)
    out = drive.copy()
    out[list(STATE)] = np.where(valid[:, None], est, np.nan)
    return out


def learn(k: int, train: list[pd.DataFrame]) -> across.Fold:
    begin = time.perf_counter()
    logs = [taught(d) for d in train]
    fitted = gyro_fit.fit(logs, logs, vehicle, R, start, progress=None,
                          **settings.kwargs(vehicle.dt))
    print(f"drive {k + 1} left out: {time.perf_counter() - begin:.0f} s, {fitted.noise}")
    return across.Fold({f"gyro, learned against the {teacher} smoother": fitted.noise}, {})


table = across.leave_one_out(drives, learn, ["ekf", "gyro"], vehicle, noise)
print(across.markdown(across.summary(table)), end="")
