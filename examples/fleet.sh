#!/usr/bin/env bash
# The worked example of docs/logs.md (make fleet): train an observer on a fleet of logs of one
# car, score it on separate test drives, then observe a new drive. The logs are simulated: a
# car whose tyres slip (car=dynamic) and whose GNSS fixes come at 10 Hz with an error that
# drifts (data=dynamic_drift), as a test car's production sensors would log beside a reference.
# Everything is written under fleet/ (its train/, val/ and test/ folders are replaced).
set -euo pipefail
PY=${PY:-python}
rm -rf fleet/train fleet/val fleet/test fleet/run
sim="$PY -m lbo.simulate manoeuvre=free_drive duration=60 data=dynamic_drift fix_rate=10"
$sim drives=20 seed=0 output=fleet/train/drive.csv | tail -1     # 20 min of driving
$sim drives=3 seed=100 output=fleet/val/drive.csv | tail -1
$sim drives=5 seed=200 output=fleet/test/drive.csv | tail -1
$sim duration=90 seed=300 output=fleet/new_drive.csv | tail -1
# train on the fleet; the end of training scores it on the test drives beside the EKFs
$PY -m lbo.train experiment=logs "data.train=[fleet/train]" "data.val=[fleet/val]" \
    "data.test=[fleet/test]" hydra.run.dir=fleet/run
# the classical peers alone, on the same test drives
$PY -m lbo.evaluate data=logs "data.test=[fleet/test]" hydra.run.dir=fleet/evaluate \
    | tail -8
# and a drive it has never seen, with a plot
$PY -m lbo.observe observer=fleet/run/checkpoints/best.ckpt input=fleet/new_drive.csv \
    output=fleet/estimates.csv plot=fleet/new_drive.png
