"""What the sensors told an observer, by name: the :class:`Measurements` of a log or a sample.

A log's measurement columns are a position fix with or without a heading (:data:`MEAS`) and
any of a receiver's optional channels (:data:`RECEIVER`: the accuracies it reports, a GNSS
velocity with its sigma, a gyro's yaw rate), each held or NaN row by row. They are read into
one :class:`Measurements` where a log or a sample enters lbo, and everything after reads its
fields, not positions in a row. The filters' own rows (:data:`lbo.filters.measure.CHANNELS`)
and a net's window columns are built from it in one place each.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from lbo.core.errors import LboError
from lbo.sim.columns import MEAS, RECEIVER


@dataclass(frozen=True, kw_only=True)
class Measurements:
    """The measurements of T steps (any leading shape ``...``: a log's T, a batch's (G, T),
    a sample's nothing), NaN where a step does not hold a channel.

    fix : (..., 2) ``[x_m, y_m]`` position fix (m).
    heading : (...) ``psi_m`` (rad), the fix's heading; NaN alone: a fix without one.
    fix_sigma : (..., 2) ``[sx_m, sy_m]`` the 1-sigma the receiver reports for its fix (m).
    heading_sigma : (...) ``spsi_m`` the 1-sigma it reports for the heading (rad).
    velocity : (..., 2) ``[ve_m, vn_m]`` a GNSS velocity east and north (m/s).
    velocity_sigma : (...) ``sv_m`` its 1-sigma (m/s).
    gyro : (...) ``r_m`` a gyro's yaw rate (rad/s, counter-clockwise).
    """

    fix: np.ndarray
    heading: np.ndarray
    fix_sigma: np.ndarray
    heading_sigma: np.ndarray
    velocity: np.ndarray
    velocity_sigma: np.ndarray
    gyro: np.ndarray

    def __post_init__(self) -> None:
        """Every field over the same steps, the pairs (``fix``, ``fix_sigma``, ``velocity``)
        two wide: a field cut or widened by mistake is one line here, not a wrong row
        downstream."""
        steps = np.shape(self.heading)
        for f in fields(self):
            want = steps + (2,) if f.name in _PAIRS else steps
            if np.shape(getattr(self, f.name)) != want:
                raise LboError(f"measurements: {f.name} must be {want} over the steps of "
                               f"heading {steps}, got {np.shape(getattr(self, f.name))}")

    @classmethod
    def of(cls, m: Any, receiver: Any = None) -> Measurements:
        """From arrays: fixes m (..., 3) ``[x_m, y_m, psi_m]`` and a receiver's channels
        (..., 7) in the order of :data:`RECEIVER` (None: none held). One line where a shape
        is not that."""
        try:
            m = np.asarray(m, dtype=float)
            r = (np.full(m.shape[:-1] + (len(RECEIVER),), np.nan) if receiver is None
                 else np.asarray(receiver, dtype=float))
        except (TypeError, ValueError):
            raise LboError(f"measurements: expected numbers, m (..., 3) [{', '.join(MEAS)}] "
                           f"and receiver (..., 7) [{', '.join(RECEIVER)}]") from None
        if m.ndim < 1 or m.shape[-1] != len(MEAS) or r.shape != m.shape[:-1] + (len(RECEIVER),):
            raise LboError(f"measurements: expected m (..., 3) [{', '.join(MEAS)}] and "
                           f"receiver (..., 7) [{', '.join(RECEIVER)}] over the same steps, "
                           f"got {m.shape} and {r.shape}")
        return cls(fix=m[..., :2], heading=m[..., 2], fix_sigma=r[..., :2],
                   heading_sigma=r[..., 2], velocity=r[..., 3:5], velocity_sigma=r[..., 5],
                   gyro=r[..., 6])

    @classmethod
    def from_frame(cls, frame: Any) -> Measurements:
        """From a log's columns (a pandas DataFrame): :data:`MEAS` (each required) and the
        receiver's :data:`RECEIVER`, each optional (a column missing: not held)."""
        missing = [c for c in MEAS if c not in frame.columns]
        if missing:
            raise LboError(f"measurements: the log has no column {', '.join(missing)} (it "
                           f"needs {', '.join(MEAS)}; NaN where a row holds no fix)")
        r = frame.reindex(columns=list(RECEIVER)).to_numpy(dtype=float)
        return cls.of(frame[list(MEAS)].to_numpy(dtype=float), r)

    @property
    def pose(self) -> np.ndarray:
        """(..., 3) ``[x_m, y_m, psi_m]``: the fix as the paper's observers read it."""
        return np.concatenate([self.fix, self.heading[..., None]], axis=-1)

    @property
    def sigma(self) -> np.ndarray:
        """(..., 3) ``[sx_m, sy_m, spsi_m]``: the reported 1-sigma of each channel of
        :attr:`pose`."""
        return np.concatenate([self.fix_sigma, self.heading_sigma[..., None]], axis=-1)

    @property
    def receiver(self) -> np.ndarray:
        """(..., 7) the receiver's channels in the order of :data:`RECEIVER`."""
        return np.concatenate([self.fix_sigma, self.heading_sigma[..., None], self.velocity,
                               self.velocity_sigma[..., None], self.gyro[..., None]], axis=-1)

    @property
    def has_fix(self) -> np.ndarray:
        """(...) bool: the step holds a position fix."""
        return np.isfinite(self.fix).all(-1)

    @property
    def has_heading(self) -> np.ndarray:
        """(...) bool: the step holds a heading ``psi_m``."""
        return np.isfinite(self.heading)

    @property
    def has_velocity(self) -> np.ndarray:
        """(...) bool: the step holds a GNSS velocity."""
        return np.isfinite(self.velocity).all(-1)

    @property
    def has_gyro(self) -> np.ndarray:
        """(...) bool: the step holds a gyro reading."""
        return np.isfinite(self.gyro)

    @property
    def reads_receiver(self) -> bool:
        """Whether any step holds any of the receiver's channels."""
        return any(bool(np.isfinite(getattr(self, name)).any()) for name in _RECEIVER_FIELDS)

    def __len__(self) -> int:
        return len(self.heading)

    def __getitem__(self, index: Any) -> Measurements:
        """The steps ``index`` selects over the leading axes (a sample: ``meas[k]``)."""
        return replace(self, **{f.name: getattr(self, f.name)[index] for f in fields(self)})


_PAIRS = ("fix", "fix_sigma", "velocity")
"""The fields two wide: ``[x_m, y_m]``, ``[sx_m, sy_m]``, ``[ve_m, vn_m]``."""
_RECEIVER_FIELDS = ("fix_sigma", "heading_sigma", "velocity", "velocity_sigma", "gyro")
"""The fields of a receiver's channels (:data:`RECEIVER`), beside the fix."""
