"""GNSS outages on the comma2k19 example segment shipped with lbo: every receiver column blanked
for 10 s, every 25 s while the car moves (:mod:`lbo.scoring.outages`), each classical observer
(and the gyro EKF with noises given as ``label=path``, files ``python -m lbo.realdrive`` wrote)
scored through them; and the gyro EKF adapted to the blanked log itself, by its innovations
(``lbo.observe adapt=true``'s fit: no truth, and no fix inside an outage), with and without
factors on the speed and the gyro (``adapt_scales=true``); and the kinematic EKF with its
inputs' terms fitted to the blanked log (``observer=ekf adapt=true``, :mod:`lbo.learn.input_fit`).
The hill drive's test span is
``python -m lbo.realdrive outages.length_s=10``.

    python benchmarks/outages.py ["truth, train span=reports/realdrive/gyro_noise.json" ...]
"""

import sys
import time

import numpy as np
from omegaconf import OmegaConf

from lbo.filters.gyro_noise import GyroNoise
from lbo.learn import gyro_fit, input_fit
from lbo.logs import comma2k19
from lbo.logs.io import receiver
from lbo.scoring import outages
from lbo.scoring.receiver import EKF, score
from lbo.serve.observer import Observer
from lbo.serve.rows import bicycle_rows
from lbo.sim.measurements import Measurements
from lbo.sim.noise import Noise
from lbo.sim.vehicle import Vehicle

vehicle = Vehicle()
noise = Noise.from_cfg(OmegaConf.load("conf/noise/paper.yaml"))  # lbo.observe's default
log = comma2k19.to_log(comma2k19.example(), vehicle).log
learned = {f"gyro, noise learned on the hill drive ({name})": GyroNoise.load(path)
           for name, path in (a.split("=", 1) for a in sys.argv[1:])}
protocol = outages.Outages(length_s=10.0, every_s=25.0)
spans, blanked = outages.cut(log, protocol, vehicle.dt)
print(f"comma2k19 example: {len(log) * vehicle.dt:.0f} s, {len(spans)} outages of "
      f"{protocol.length_s:g} s at {', '.join(f'{s * vehicle.dt:.0f}' for s in spans[:, 0])} s")
defaults = GyroNoise.from_q(noise.Q)
for label, start in (("adapt=true", defaults), ("adapt=true adapt_scales=true",
                                                defaults.with_scales())):
    began = time.perf_counter()
    fitted = gyro_fit.adapt(blanked, start, vehicle, noise)  # 12 epochs, as lbo.observe's
    print(f"{label}: {time.perf_counter() - began:.0f} s, kept epoch {fitted.best_epoch}: "
          f"{fitted.noise}")
    learned[f"gyro, adapted to the log around the outages ({label})"] = fitted.noise
_, estimates = score(blanked, ["ekf", "gyro"], vehicle, noise, learned)
# the kinematic EKF with its inputs' terms fitted to the blanked log (observer=ekf adapt=true)
m = blanked[["x_m", "y_m", "psi_m"]].to_numpy(dtype=float)
u = blanked[["V", "delta"]].to_numpy(dtype=float)
channels = receiver(blanked)
began = time.perf_counter()
terms = input_fit.fit(bicycle_rows(Measurements.of(m, channels), u, vehicle.wheelbase), u,
                      vehicle, noise).terms
print(f"observer=ekf adapt=true: {time.perf_counter() - began:.0f} s, {terms.describe()}")
est, ok = Observer.load("ekf", vehicle, noise, inputs=terms).run(m, u, receiver=channels)
estimates[f"{EKF}, inputs' terms fitted to the log (adapt=true)"] = np.where(ok[:, None], est,
                                                                             np.nan)
print(outages.markdown(outages.score(estimates, log, spans, vehicle.dt, reference=EKF)), end="")
