"""``lbo.observe observer=gyro adapt=true`` on each of the hill drive's drives, its fit
(:func:`lbo.learn.gyro_fit.adapt`) with the receiver's factors learned by the innovations
(``adapt_receiver_noise=learned``, the default) and set by the variogram of the drive itself
(``adapt_receiver_noise=variogram``); each drive scored against its truth, which no fit reads.

    python benchmarks/adapt_variogram.py      # about 4 min on a 2-core CPU
"""

import time

import pandas as pd
from omegaconf import OmegaConf

from lbo.filters.gyro_noise import GyroNoise
from lbo.learn import gyro_fit
from lbo.logs import hguide
from lbo.scoring import drives as across
from lbo.scoring.receiver import EKF, ratio_to, score
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

vehicle = Vehicle()
noise = Noise.from_cfg(OmegaConf.load("conf/noise/paper.yaml"))  # lbo.observe's default
drives = hguide.drives(hguide.to_log(hguide.read(), vehicle))
tables = []
for k, drive in enumerate(drives):
    adapted = {}
    for how in ("learned", "variogram"):
        begin = time.perf_counter()
        fitted = gyro_fit.adapt(drive, GyroNoise.from_q(noise.Q), vehicle, noise,
                                receiver_noise=how)
        print(f"drive {k + 1}, {how}: {time.perf_counter() - begin:.0f} s, kept epoch "
              f"{fitted.best_epoch}", flush=True)
        adapted[f"gyro, adapted to the drive (adapt_receiver_noise={how})"] = fitted.noise
    table, _ = score(drive, ["ekf", "gyro"], vehicle, noise, adapted)
    table["vs_ekf"] = ratio_to(table, EKF)
    table.insert(0, "drive", k + 1)
    tables.append(table)
print(across.markdown(across.summary(pd.concat(tables, ignore_index=True))), end="")
