"""What a simulated log is drawn from: the car (config group ``car``) and its sensors' errors
(group ``sensors``), together a :class:`Truth`.

``kinematic`` is the paper's kinematic bicycle (:mod:`lbo.sim.vehicle`), the very model inside the
classical filters; ``dynamic`` is a car that slips (:mod:`lbo.sim.dynamic`). Both log the same
schema: the rear axle's ``x, y, psi`` as the state and ``V, delta`` as the inputs. A truth
model is found by its name among the installed packages' entry points (group
``lbo.truths``, :mod:`lbo.core.plugins`), lbo's two as a user's: any car that keeps
:class:`Car` drives the simulator, the data sets and the EKF told the car.

Three sensor errors beside the white measurement noise, each off by default (``sensors=white``;
``sensors=drift`` turns the drift on):

- GNSS drift: a first-order Gauss-Markov error on x and y,
  ``b_{k+1} = phi b_k + sqrt(1 - phi^2) sigma eps_k``, ``phi = exp(-dt / tau)``, stationary from
  the first step (standard deviation ``gnss_sigma``, correlation time ``gnss_tau``); like the
  white noise it is scaled by alpha;
- a steering offset: the logged delta is the road-wheel angle plus ``steering_offset`` (rad);
- a speed scale-factor error: the logged V is ``(1 + speed_scale)`` times the true speed.

Beside the car's own settings, ``car.process_scale`` sets how much of the noise preset's process
noise the truth itself carries: the paper's kinematic truth adds all of it (1), a car's pose
moves as its dynamics say, up to a small unmodelled rest. The classical filters are still told
the preset's Q, the one a filter designer would choose. A car that slips may also carry
disturbances of its lateral states (``car.lateral_sigma``: white noise on v_y and r after each
step, as gusts, a road's bank and tyres that vary push a real car), which only the EKF told the
car is told.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, cast, runtime_checkable

import numpy as np

from lbo.core import plugins
from lbo.core.checks import number, require
from lbo.core.errors import LboError


@runtime_checkable
class Car(Protocol):
    """What a car that slips keeps, lbo's single-track (:class:`lbo.sim.dynamic.SingleTrack`)
    and a user's (registered in the entry-point group ``lbo.truths``; docs/plugins.md): a
    frozen dataclass whose fields are its ``car.*`` settings (each checked in its
    ``__post_init__``), with the state ``[x, y, psi, v_y, r]``: the rear axle's pose, then the
    lateral speed of the centre of gravity (m/s) and the yaw rate (rad/s)."""

    # a dataclass (Truth.to_dict reads its fields), to the type checker only: isinstance
    # checks the members below, and from_cfg refuses a registered car that is no dataclass
    if TYPE_CHECKING:
        __dataclass_fields__: ClassVar[dict[str, Any]]

    @property
    def wheelbase(self) -> float:
        """m: the vehicle's (``vehicle.wheelbase``) it must be."""
        ...

    @property
    def understeer_gradient(self) -> float:
        """rad per m/s^2 of lateral acceleration: the friction-circle generator steers by it."""
        ...

    def start(self, z0: np.ndarray, u0: np.ndarray) -> np.ndarray:
        """(..., 5) states at poses z0 (..., 3) for the first inputs u0 (..., 2) [V, delta]."""
        ...

    def step(self, s: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """(..., 5) states one period dt (s) on from s (..., 5), inputs u (..., 2) held."""
        ...

    def rear_slip(self, s: np.ndarray, u: np.ndarray) -> np.ndarray:
        """(...,) the angle (rad) of the rear axle's velocity off the heading."""
        ...


class Kinematic:
    """The paper's kinematic bicycle as a truth model: no car (:mod:`lbo.sim.vehicle` drives
    it, as the classical filters model it). Registered as ``kinematic`` so that lbo's two
    truth models are found by the path a user's is."""


@dataclass(frozen=True, kw_only=True)
class Sensors:
    """Sensor errors beyond the white measurement noise (all zero: none).

    Attributes
    ----------
    gnss_sigma : standard deviation (m) of the Gauss-Markov GNSS drift on x and y at alpha=1.
    gnss_tau : its correlation time (s).
    steering_offset : added to the logged road-wheel angle (rad).
    speed_scale : relative error of the logged speed (0.02: V reads 2 % high).
    """

    gnss_sigma: float = 0.0
    gnss_tau: float = 30.0
    steering_offset: float = 0.0
    speed_scale: float = 0.0

    def __post_init__(self) -> None:
        number(self.gnss_sigma, "sensors.gnss_sigma", low=0.0)
        number(self.gnss_tau, "sensors.gnss_tau", low=0.0, low_open=True)
        number(self.steering_offset, "sensors.steering_offset", low=-0.2, high=0.2)
        number(self.speed_scale, "sensors.speed_scale", low=-0.5, high=0.5)

    @property
    def off(self) -> bool:
        return self.gnss_sigma == 0 and self.steering_offset == 0 and self.speed_scale == 0

    def logged_inputs(self, u: np.ndarray) -> np.ndarray:
        """What the car's sensors log for true inputs u (..., 2) [V, delta]."""
        if self.steering_offset == 0 and self.speed_scale == 0:
            return u
        return np.stack([u[..., 0] * (1 + self.speed_scale), u[..., 1] + self.steering_offset],
                        axis=-1)

    def drift(self, shape: tuple[int, int], dt: float, alpha: np.ndarray | float,
              rng: np.random.Generator) -> np.ndarray:
        """(B, T, 3) GNSS drift on x and y (zero on psi) of B logs of T steps at noise scales
        alpha (scalar or (B,)); zeros when ``gnss_sigma`` is 0 (and ``rng`` is not drawn)."""
        out = np.zeros(shape + (3,))
        if self.gnss_sigma > 0:
            b = gauss_markov(shape + (2,), dt, self.gnss_tau, self.gnss_sigma, rng)
            out[..., :2] = np.reshape(alpha, (-1, 1, 1)) * b
        return out


@dataclass(frozen=True, kw_only=True)
class Truth:
    """The model a log is drawn from and its sensors' errors.

    Attributes
    ----------
    name : the truth model's registered name (``kinematic``, ``dynamic`` or a user's).
    car : the car that slips (:class:`Car`), or None: the kinematic bicycle.
    sensors : the sensor errors.
    process_scale : the truth's process noise is this times the noise preset's
        ``process_sigma`` (1: the paper's random walk on x, y and psi).
    lateral_sigma : (2,) standard deviations of the white disturbances added to a car's
        lateral states v_y (m/s) and r (rad/s) after each step; none by default, and none for
        the kinematic bicycle, which has no lateral states.
    """

    name: str = "kinematic"
    car: Car | None = None
    sensors: Sensors = field(default_factory=Sensors)
    process_scale: float = 1.0
    lateral_sigma: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "process_scale", number(self.process_scale,
                                                         "car.process_scale", low=0.0))
        form = "two standard deviations >= 0 [v_y (m/s), r (rad/s)] per step"
        given = self.lateral_sigma
        require(isinstance(given, (list, tuple)) and len(given) == 2, "car.lateral_sigma",
                form, given)
        v_y, r = (number(s, "car.lateral_sigma", low=0.0, form=form) for s in given)
        require(self.car is not None or (v_y, r) == (0.0, 0.0), "car.lateral_sigma",
                "[0, 0] for the kinematic bicycle, which has no lateral states", [v_y, r])
        object.__setattr__(self, "lateral_sigma", (v_y, r))

    @property
    def default(self) -> bool:
        """The paper's setting: kinematic bicycle, its process noise, white measurement noise,
        exact inputs."""
        return self.name == "kinematic" and self.sensors.off and self.process_scale == 1.0

    def process_sigma(self, noise: Any) -> np.ndarray:
        """(3,) process sigmas (m, m, rad) of the truth's motion for a noise preset."""
        return self.process_scale * np.asarray(noise.process_sigma, dtype=float)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, **asdict(self.sensors)}
        if self.process_scale != 1.0:  # the digests of sets drawn before this field stay
            out["process_scale"] = self.process_scale
        if any(self.lateral_sigma):  # ... and before this one
            out["lateral_sigma"] = list(self.lateral_sigma)
        if self.car is not None:
            out.update(asdict(self.car))
        return out


def gauss_markov(shape: tuple[int, ...], dt: float, tau: float, sigma: float,
                 rng: np.random.Generator) -> np.ndarray:
    """First-order Gauss-Markov sequences along axis 1 of ``shape`` (B, T, ...), stationary:
    ``b_0 ~ N(0, sigma^2)``, ``b_{k+1} = phi b_k + sqrt(1 - phi^2) sigma eps``, ``phi =
    exp(-dt / tau)``. Its variance is sigma^2 at every step and its autocorrelation at lag
    ``tau`` is exp(-1)."""
    phi = np.exp(-dt / tau)
    eps = rng.standard_normal(shape)
    eps[:, 1:] *= np.sqrt(1.0 - phi**2)
    b = np.empty(shape)
    b[:, 0] = eps[:, 0]
    for k in range(1, shape[1]):  # sequential in time, vectorised over the rest
        b[:, k] = phi * b[:, k - 1] + eps[:, k]
    return sigma * b


def from_cfg(car: Any, sensors: Any, wheelbase: float) -> Truth:
    """The Truth of the Hydra groups ``car`` and ``sensors`` (either None or absent: the
    kinematic bicycle, white noise alone).

    ``car.name`` is looked up among the registered truth models (entry-point group
    ``lbo.truths``; nothing a config names is imported otherwise). Raises LboError naming the
    field for an unknown model, a bad value, a car that does not keep :class:`Car`, axle
    distances that do not sum to the vehicle's wheelbase, or a key of neither group.
    """
    s = dict(sensors or {})
    unknown = [k for k in s if k not in Sensors.__dataclass_fields__]
    if unknown:
        raise LboError(f"sensors.{unknown[0]}: not a sensor error; accepted: "
                       f"{', '.join(Sensors.__dataclass_fields__)}")
    c = dict(car or {})
    name = c.pop("name", "kinematic")
    scale = c.pop("process_scale", 1.0)
    lateral = c.pop("lateral_sigma", (0.0, 0.0))
    if isinstance(lateral, Sequence) and not isinstance(lateral, str):  # a ListConfig too
        lateral = tuple(lateral)
    cls: type[Any] = plugins.load("truth", name, "car.name")  # a class, Kinematic or a car
    if cls is Kinematic:
        if c:
            raise LboError(f"car.{next(iter(c))}: not a field of car={name}; "
                           "accepted: name, process_scale")
        return Truth(name=name, car=None, sensors=Sensors(**s), process_scale=scale,
                     lateral_sigma=lateral)
    if not dataclasses.is_dataclass(cls):
        raise LboError(f"car.name: truth model {name!r} is registered as {cls!r}, not a "
                       "dataclass of its settings (docs/plugins.md)")
    car_keys = [f.name for f in dataclasses.fields(cls)]
    unknown = [k for k in c if k not in car_keys]
    if unknown:
        raise LboError(f"car.{unknown[0]}: not a field of car={name}; accepted: "
                       f"name, process_scale, lateral_sigma, {', '.join(car_keys)}")
    try:
        built = cast(Car, cls(**c))  # that it keeps Car's members is checked below
    except (TypeError, ValueError) as e:  # a plug-in's own check, said in lbo's one line
        raise LboError(f"car: truth model {name!r} refused its settings ({e})") from None
    missing = [m for m in ("wheelbase", "understeer_gradient", "start", "step", "rear_slip")
               if not hasattr(built, m)]
    if missing:
        raise LboError(f"car.name: truth model {name!r} lacks {', '.join(missing)} (a car "
                       "keeps lbo.sim.truth.Car: docs/plugins.md)")
    axles = hasattr(built, "l_f") and hasattr(built, "l_r")  # the fields a user sets, if any
    require(abs(float(built.wheelbase) - wheelbase) < 1e-6,
            "car.l_f + car.l_r" if axles else f"car={name}'s wheelbase",
            f"the vehicle's wheelbase ({wheelbase} m)", built.wheelbase)
    return Truth(name=name, car=built, sensors=Sensors(**s), process_scale=scale,
                 lateral_sigma=lateral)


def of_config(cfg: Any, wheelbase: float) -> Truth:
    """The Truth of a composed config's ``car`` and ``sensors`` groups (see :func:`from_cfg`)."""
    return from_cfg(cfg.get("car"), cfg.get("sensors"), wheelbase)


def config_dict(cfg: Any) -> dict[str, Any] | None:
    """A composed config's ``car`` and ``sensors`` groups as one mapping, the car's keys first
    (the form :func:`from_dict` reads and a checkpoint keeps as its ``truth``); None: neither."""
    from omegaconf import OmegaConf

    groups = [cfg.get(g) for g in ("car", "sensors")]
    if all(g is None for g in groups):
        return None
    return {k: v for g in groups if g is not None
            for k, v in cast(dict, OmegaConf.to_container(g, resolve=True)).items()}


def from_dict(truth: dict[str, Any] | None, wheelbase: float) -> Truth:
    """The Truth of :meth:`Truth.to_dict`'s mapping (a data set's manifest, a checkpoint's
    ``truth``): the car's fields and the sensors' in one; None: the paper's."""
    d = dict(truth or {})
    sensors = {k: d.pop(k) for k in list(d) if k in Sensors.__dataclass_fields__}
    return from_cfg(d, sensors, wheelbase)


def of_folder(folder: Any, wheelbase: float) -> Truth:
    """The Truth a data-set folder was drawn from, as its ``manifest.json`` records it (the
    paper's kinematic bicycle when the manifest names none, or is missing)."""
    import json
    from pathlib import Path

    manifest = Path(folder) / "manifest.json"
    if not manifest.is_file():
        return Truth()
    return from_dict(json.loads(manifest.read_text()).get("truth"), wheelbase)
