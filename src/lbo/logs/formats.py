"""Logs as they arrive: a logger's column names, units and conventions turned into lbo's.

lbo reads a log in one form (``t`` in s; ``x_m, y_m`` in metres east and north of a local
origin; ``psi_m`` in rad counter-clockwise from east; ``V`` in m/s; ``delta``, the road-wheel
angle, in rad, positive to the left). A :class:`LogFormat` says how a log differs from it:

- ``columns``: lbo's field -> the log's column name (``{"V": "speed"}``);
- ``units``: ``V`` in ``mps``, ``kmh`` or ``mph``; ``psi`` and ``delta`` in ``rad`` or ``deg``
  (``psi`` covers the measured heading and the true one);
- ``steering_ratio``: the log's ``delta`` is the steering wheel's angle, this many times the
  road wheels' (1: it is the road wheels');
- ``heading``: ``enu`` (counter-clockwise from east) or ``compass`` (clockwise from north);
- geodetic positions: columns ``lat, lon`` (degrees) in place of ``x_m, y_m``, and
  ``lat_true, lon_true`` in place of ``x, y``, become local east/north metres around the
  log's first fix (pymap3d, on the WGS84 ellipsoid at height 0); each heading, measured from
  the local north (compass) or east (enu) at its own fix, is turned into that frame by the
  meridians' convergence there (:meth:`Origin.heading_from`; 0.3 rad 600 m across a pole's
  meridians, 2e-5 rad 100 m across Paris's).

:meth:`LogFormat.apply` returns the log in lbo's form, and the :class:`Origin` of a geodetic
one, whose :meth:`~Origin.to_geodetic` turns estimates back. ``python -m lbo.observe`` and
``data=logs`` take the same settings; with :class:`lbo.Observer`, apply the format first.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
import pandas as pd

from lbo.core.angles import wrap_angle
from lbo.core.checks import number
from lbo.core.errors import LboError

FIELDS = ("t", "x_m", "y_m", "psi_m", "V", "delta", "x", "y", "psi",
          "lat", "lon", "lat_true", "lon_true")
"""The fields ``columns.<field>`` maps: lbo's log columns and the geodetic ones."""
SPEED_UNITS = {"mps": 1.0, "kmh": 1 / 3.6, "mph": 0.44704}
"""Speed units and their factor to m/s."""
ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180}
HEADINGS = ("enu", "compass")
GEODETIC = (("lat", "lon", "x_m", "y_m"), ("lat_true", "lon_true", "x", "y"))
"""(latitude, longitude, east, north) column quadruples: the fix and the truth."""


@dataclass(frozen=True)
class Origin:
    """The geodetic point (deg, deg) a log's local east/north metres are measured from."""

    lat: float
    lon: float

    def to_geodetic(self, east: np.ndarray, north: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(lat, lon) in degrees of local (east, north) metres, each (T,)."""
        import pymap3d

        lat, lon, _ = pymap3d.enu2geodetic(np.asarray(east, float), np.asarray(north, float),
                                           0.0, self.lat, self.lon, 0.0)
        return np.asarray(lat), np.asarray(lon)

    def heading_from(self, psi: np.ndarray, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        """Headings in this origin's frame (T,) rad, of headings ``psi`` (T,) rad counter-
        clockwise from the local east at each point (lat, lon) (T,) degrees.

        The local east and north turn with the point: near a pole, a few hundred metres
        east of the origin, the local north leans by tens of degrees from the frame's y axis
        (the meridians converge). The heading's direction is projected onto the origin's
        tangent plane (pymap3d, WGS84), exactly; the result stays on ``psi``'s branch (the
        turn is added to it), and NaN stays NaN."""
        return _turn(psi, lat, lon, self, to_origin=True)

    def heading_at(self, psi: np.ndarray, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        """The reverse of :meth:`heading_from`: headings ``psi`` (T,) rad in this origin's frame
        -> counter-clockwise from the local east at each point (lat, lon) (T,) degrees (for a
        compass bearing there: ``pi/2 -`` the result)."""
        return _turn(psi, lat, lon, self, to_origin=False)


def _turn(psi: np.ndarray, lat: np.ndarray, lon: np.ndarray, origin: Origin,
          to_origin: bool) -> np.ndarray:
    """``psi`` (T,) turned between the local ENU frame at each (lat, lon) (T,) and the
    origin's: the direction vector taken to ECEF and back (pymap3d), its angle in the target
    frame's horizontal plane; the difference to ``psi``, wrapped, added to ``psi``."""
    import pymap3d

    psi, lat, lon = (np.asarray(a, float) for a in (psi, lat, lon))
    frames = ((lat, lon), (origin.lat, origin.lon))
    (lat_a, lon_a), (lat_b, lon_b) = frames if to_origin else frames[::-1]
    x, y, z = pymap3d.enu2ecefv(np.cos(psi), np.sin(psi), 0.0, lat_a, lon_a)
    east, north, _ = pymap3d.ecef2enuv(x, y, z, lat_b, lon_b)
    return psi + wrap_angle(np.arctan2(north, east) - psi)


def to_local(lat: np.ndarray, lon: np.ndarray, origin: Origin) -> tuple[np.ndarray, np.ndarray]:
    """Local (east, north) metres (T,) of geodetic (lat, lon) degrees (T,) around ``origin``,
    on the WGS84 ellipsoid at height 0; NaN stays NaN (a step without a fix)."""
    import pymap3d

    e, n, _ = pymap3d.geodetic2enu(np.asarray(lat, float), np.asarray(lon, float), 0.0,
                                   origin.lat, origin.lon, 0.0)
    return np.asarray(e), np.asarray(n)


@dataclass(frozen=True, kw_only=True)
class LogFormat:
    """How a log differs from lbo's form (see the module's docstring)."""

    columns: Mapping[str, str] = field(default_factory=dict)
    units: Mapping[str, str] = field(default_factory=dict)
    steering_ratio: float = 1.0
    heading: str = "enu"

    def __post_init__(self) -> None:
        for key, name in self.columns.items():
            if key not in FIELDS:
                raise LboError(f"columns.{key}: unknown field; expected one of "
                               f"{', '.join(FIELDS)}")
            if not isinstance(name, str) or not name.strip():
                raise LboError(f"columns.{key} must be the log's column name, got {name!r}")
        kinds = {"V": SPEED_UNITS, "psi": ANGLE_UNITS, "delta": ANGLE_UNITS}
        for key, unit in self.units.items():
            if key not in kinds:
                raise LboError(f"units.{key}: unknown field; expected one of V, psi, delta")
            if unit not in kinds[key]:
                raise LboError(f"units.{key} must be one of {', '.join(kinds[key])}, "
                               f"got {unit!r}")
        number(self.steering_ratio, "steering_ratio", low=0.0, low_open=True,
               form="a number > 0 (the steering wheel's angle over the road wheels'; 1: delta "
               "is the road wheels')")
        if self.heading not in HEADINGS:
            raise LboError(f"heading must be enu (counter-clockwise from east) or compass "
                           f"(clockwise from north), got {self.heading!r}")

    @classmethod
    def from_cfg(cls, cfg: Any) -> LogFormat:
        """From a config node with ``columns``, ``units``, ``steering_ratio``, ``heading``
        (each optional; a missing one keeps lbo's form)."""
        from omegaconf import OmegaConf

        def plain(key: str) -> dict:
            node = cfg.get(key) if cfg is not None else None
            if node is None:
                return {}
            value = OmegaConf.to_container(node) if OmegaConf.is_config(node) else node
            if not isinstance(value, dict):
                raise LboError(f"{key} must be a mapping ({key}.<field>=<value>), got {value!r}")
            return {str(k): v for k, v in value.items() if v is not None}

        get = (lambda k, d: cfg.get(k, d)) if cfg is not None else (lambda k, d: d)
        return cls(columns=plain("columns"), units=plain("units"),
                   steering_ratio=get("steering_ratio", 1.0), heading=get("heading", "enu"))

    @property
    def is_plain(self) -> bool:
        """Whether the log is already in lbo's form (no mapping, no conversion)."""
        return (not self.columns and set(self.units.values()) <= {"mps", "rad"}
                and self.steering_ratio == 1 and self.heading == "enu")

    def describe(self) -> str:
        """One line of what this format changes, or '' for lbo's form."""
        parts = [f"{k} <- {v}" for k, v in self.columns.items()]
        parts += [f"{k} in {u}" for k, u in self.units.items() if u not in ("mps", "rad")]
        if self.steering_ratio != 1:
            parts.append(f"steering ratio {self.steering_ratio:g}")
        if self.heading != "enu":
            parts.append(f"{self.heading} headings")
        return ", ".join(parts)

    def apply(self, df: pd.DataFrame, source: str = "input") -> tuple[pd.DataFrame,
                                                                       Origin | None]:
        """The log ``df`` in lbo's form, and the origin of its local frame when its
        positions were geodetic (else None). Columns lbo does not read pass through.

        Raises
        ------
        LboError
            A mapped column that is not in the log, both ``lat``/``lon`` and ``x_m``/``y_m``,
            one of ``lat``/``lon`` without the other, a latitude or longitude outside its
            range, a non-numeric column it converts.
        """
        out = df
        if self.columns:
            missing = [f"columns.{k}={v}" for k, v in self.columns.items() if v not in df.columns]
            if missing:
                raise LboError(f"{source}: {missing[0]}: no column {missing[0].split('=', 1)[1]!r}"
                               f" in the log (found {', '.join(map(str, df.columns))})")
            mapped = set(self.columns.values())
            # a column of lbo's name that another column replaces gives way to it
            keep = [c for c in df.columns if c in mapped or c not in self.columns]
            out = df[keep].rename(columns={v: k for k, v in self.columns.items()})
        else:
            out = df.copy()
        origin, places = self._geodetic(out, source)
        for col, kind in (("V", "V"), ("psi_m", "psi"), ("psi", "psi"), ("delta", "delta")):
            unit = self.units.get(kind)
            factor = (SPEED_UNITS if kind == "V" else ANGLE_UNITS).get(unit, 1.0) \
                if unit else 1.0
            if col == "delta":
                factor /= self.steering_ratio
            convert = factor != 1.0 or (kind == "psi" and (self.heading == "compass"
                                                           or col in places))
            if col not in out.columns or not convert:
                continue
            values = _numeric(out, col, source) * factor
            if kind == "psi" and self.heading == "compass":  # clockwise from north -> ENU
                values = wrap_angle(math.pi / 2 - values)
            if col in places:  # from the local east at each fix to the first fix's east
                lat, lon = places[col]
                here = cast(Origin, origin)  # _geodetic gives places with their origin
                known = np.isfinite(lat) & np.isfinite(lon)
                # a heading without a place is refused by the checks as such
                values = np.where(known, here.heading_from(values, np.where(known, lat, 0.0),
                                                             np.where(known, lon, 0.0)), values)
            out[col] = values
        return out, origin

    def _geodetic(self, out: pd.DataFrame, source: str) -> tuple[Origin | None, dict]:
        """Replace ``lat, lon`` (and ``lat_true, lon_true``) in ``out`` by local metres.

        Returns the origin (None: no geodetic positions) and, for each heading column
        (``psi_m``, ``psi``), the (lat, lon) (T,) degrees whose local east it was measured
        from: the fixes' for ``psi_m``, the true positions' for ``psi`` (the fixes', filled
        in between them, when the log has no true lat/lon)."""
        origin = None
        places: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for lat_c, lon_c, east_c, north_c in GEODETIC:
            has = [c in out.columns for c in (lat_c, lon_c)]
            if not any(has):
                continue
            if not all(has):
                there, gone = (lat_c, lon_c) if has[0] else (lon_c, lat_c)
                raise LboError(f"{source}: column {there!r} without {gone!r}; geodetic "
                               "positions need both (degrees)")
            if east_c in out.columns or north_c in out.columns:
                raise LboError(f"{source}: both {lat_c}/{lon_c} and {east_c}/{north_c}; give "
                               "positions one way (map the one to use with columns.<field>=)")
            lat, lon = _numeric(out, lat_c, source), _numeric(out, lon_c, source)
            for name, v, limit in ((lat_c, lat, 90.0), (lon_c, lon, 180.0)):
                bad = np.abs(v) > limit  # NaN compares False: a step without a fix
                if bad.any():
                    r = int(np.flatnonzero(bad)[0])
                    raise LboError(f"{source}: row {r}: {name}={v[r]:g} is outside "
                                   f"[-{limit:g}, {limit:g}]; {name} is in degrees")
            if origin is None:
                fixed = np.flatnonzero(np.isfinite(lat) & np.isfinite(lon))
                if not len(fixed):
                    raise LboError(f"{source}: no row with both {lat_c} and {lon_c}")
                origin = Origin(float(lat[fixed[0]]), float(lon[fixed[0]]))
            e, n = to_local(lat, lon, origin)
            at = cast(int, out.columns.get_loc(lat_c))  # a column name read appears once
            del out[lat_c], out[lon_c]  # in place: the caller's frame is the one converted
            out.insert(at, east_c, e)
            out.insert(at + 1, north_c, n)
            places["psi_m" if lat_c == "lat" else "psi"] = (lat, lon)
        if "psi_m" in places and "psi" not in places:
            lat, lon = places["psi_m"]
            rows = np.arange(len(lat))
            fixed = np.isfinite(lat) & np.isfinite(lon)
            # the meridians' turn varies smoothly along the path: interpolate it by row (lon
            # unwrapped so that a path across the antimeridian interpolates the short way)
            lon_u = np.degrees(np.unwrap(np.radians(lon[fixed])))
            places["psi"] = (np.interp(rows, rows[fixed], lat[fixed]),
                             np.interp(rows, rows[fixed], lon_u))
        return origin, places


def _numeric(df: pd.DataFrame, col: str, source: str) -> np.ndarray:
    if df[col].dtype.kind not in "iuf":
        raise LboError(f"{source}: column {col!r} is not numeric (dtype {df[col].dtype})")
    return df[col].to_numpy(dtype=float)
