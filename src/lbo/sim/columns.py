"""Every column name of lbo's tables, in one home: a data set's, a log's, a receiver's, an
observer's output. Names only (nothing heavy is imported here), so that any layer can read them.
"""

from __future__ import annotations

STATE = ("x", "y", "psi")
"""The true pose (m, m, rad): the state every observer estimates."""
MEAS = ("x_m", "y_m", "psi_m")
"""A position fix: x_m and y_m, with or without psi_m (the classical observers take a position
without a heading); all three NaN: a step without a fix."""
INPUT = ("V", "delta")
"""The inputs: speed (m/s) and steering (rad)."""
RECEIVER = ("sx_m", "sy_m", "spsi_m", "ve_m", "vn_m", "sv_m", "r_m")
"""Optional columns of a receiver's log, each held or NaN row by row: the 1-sigma accuracy
it reports for its fix (sx_m, sy_m in m; spsi_m in rad, of psi_m), a GNSS velocity ve_m,
vn_m (m/s east, north) with its 1-sigma sv_m (m/s), and a gyro's yaw rate r_m (rad/s,
counter-clockwise, at any rate). The classical observers take them (:mod:`lbo.filters.measure`;
r_m: the ``gyro`` observer, :mod:`lbo.filters.gyro`)."""
WINDOW = (*MEAS, *INPUT)
"""The channels of one step of a learned observer's window (N, 5), in order."""
LOG = ("t", *WINDOW)
"""A user's log: time (s), the fix, the inputs (``lbo.observe``'s input)."""
SET = ("traj", "k", "t", *STATE, *INPUT, *MEAS)
"""A data set's rows: trajectory, step, time, truth, inputs, fix."""
SCORED_SET = (*SET, "alpha", "scored")
"""A validation or test set's rows: also the noise scale and whether the row is scored."""
LATERAL = ("v_y", "r")
"""The true lateral states of a car that slips (``car=dynamic``), which a validation or test
set drawn from one also holds: the centre of gravity's lateral speed (m/s) and the yaw rate
(rad/s). No observer reads them: they score its side slip and yaw rate."""
LATERAL_ESTIMATE = ("beta", *LATERAL)
"""The lateral states an observer that carries a single-track body estimates and
``lbo.observe`` adds to its output: the side slip at the centre of gravity (rad), v_y (m/s) and
r (rad/s)."""
LATERAL_VARIANCE = tuple(f"var_{name}" for name in LATERAL_ESTIMATE)
"""Their variances (rad^2, m^2/s^2, rad^2/s^2), which ``lbo.observe`` adds where the
observer's checkpoint holds its body's error on the validation set
(:func:`lbo.serve.estimate.lateral_variance`)."""
OUTPUT = ("t", *STATE, "valid")
"""``lbo.observe``'s output: time, the estimate, and whether the observer has one yet."""
COVARIANCE = ("var_x", "var_y", "var_psi", "cov_xy")
"""The covariance's entries an observer that gives one adds to the output."""
SERVED = (*OUTPUT[1:], *COVARIANCE)
"""A served answer (MLflow model serving): the output without times, with the covariance."""
