"""The comma2k19 example segment, nothing learned on it: the classical observers, the gyro EKF
with noises learned on the hill drive (files that ``python -m lbo.realdrive`` wrote, given as
``label=path``), and the gyro EKF adapted to the segment itself (``lbo.observe adapt=true``'s
fit, :func:`lbo.learn.gyro_fit.adapt`).

    python benchmarks/comma_transfer.py "truth, train span=reports/realdrive/gyro_noise.json" ...
"""

import sys
import time

from omegaconf import OmegaConf

from lbo.filters.gyro_noise import GyroNoise
from lbo.learn import gyro_fit
from lbo.logs import comma2k19
from lbo.scoring.receiver import EKF, RAW, RMSE, markdown, ratio_to, score
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

vehicle = Vehicle()
noise = Noise.from_cfg(OmegaConf.load("conf/noise/paper.yaml"))  # lbo.observe's default
log = comma2k19.to_log(comma2k19.example(), vehicle).log
learned = {f"gyro, noise learned on the hill drive ({name})": GyroNoise.load(path)
           for name, path in (a.split("=", 1) for a in sys.argv[1:])}
start = time.perf_counter()
adapted = gyro_fit.adapt(log, GyroNoise.from_q(noise.Q), vehicle, noise)  # adapt=true's fit
print(f"adapt: {time.perf_counter() - start:.1f} s, kept epoch {adapted.best_epoch}: "
      f"{adapted.noise}")
learned["gyro, adapted to the segment (adapt=true)"] = adapted.noise
table, _ = score(log, ["ekf", "gyro"], vehicle, noise, learned)
table["vs_ekf"], table["vs_raw"] = ratio_to(table, EKF), ratio_to(table, RAW)
print(markdown(table, "vs_ekf", "vs_raw"))
rmse = table[list(RMSE)]
print("each variable's RMSE over the raw fixes':")
print((rmse / rmse[table.estimator == RAW].to_numpy()).round(3)
      .assign(estimator=table.estimator).to_string())
