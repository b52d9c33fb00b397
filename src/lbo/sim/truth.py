"""What a simulated log is drawn from: the vehicle model, and the sensors' errors.

``kinematic`` is the paper's kinematic bicycle (:mod:`lbo.sim.vehicle`), the very model inside the
classical filters; ``dynamic`` is a car that slips (:mod:`lbo.sim.dynamic`). Both log the same
schema: the rear axle's ``x, y, psi`` as the state and ``V, delta`` as the inputs. A truth
model is found by its name among the installed packages' entry points (group
``lbo.truths``, :mod:`lbo.core.plugins`), lbo's two as a user's: any car that keeps
:class:`Car` drives the simulator, the data sets and the EKF told the car.

Three sensor errors beside the white measurement noise, each off by default:

- GNSS drift: a first-order Gauss-Markov error on x and y,
  ``b_{k+1} = phi b_k + sqrt(1 - phi^2) sigma eps_k``, ``phi = exp(-dt / tau)``, stationary from
  the first step (standard deviation ``gnss_sigma``, correlation time ``gnss_tau``); like the
  white noise it is scaled by alpha;
- a steering offset: the logged delta is the road-wheel angle plus ``steering_offset`` (rad);
- a speed scale-factor error: the logged V is ``(1 + speed_scale)`` times the true speed.

Beside the sensors, ``process_scale`` sets how much of the noise preset's process noise the
truth itself carries: the paper's kinematic truth adds all of it (1), a car's pose moves as its
dynamics say, up to a small unmodelled rest. The classical filters are still told the preset's
Q, the one a filter designer would choose.
"""

from __future__ import annotations

import dataclasses
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
    frozen dataclass whose fields are its ``truth.*`` settings (each checked in its
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


@dataclass(frozen=True)
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
        number(self.gnss_sigma, "truth.gnss_sigma", low=0.0)
        number(self.gnss_tau, "truth.gnss_tau", low=0.0, low_open=True)
        number(self.steering_offset, "truth.steering_offset", low=-0.2, high=0.2)
        number(self.speed_scale, "truth.speed_scale", low=-0.5, high=0.5)

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


@dataclass(frozen=True)
class Truth:
    """The model a log is drawn from and its sensors' errors.

    Attributes
    ----------
    name : the truth model's registered name (``kinematic``, ``dynamic`` or a user's).
    car : the car that slips (:class:`Car`), or None: the kinematic bicycle.
    sensors : the sensor errors.
    process_scale : the truth's process noise is this times the noise preset's
        ``process_sigma`` (1: the paper's random walk on x, y and psi).
    """

    name: str = "kinematic"
    car: Car | None = None
    sensors: Sensors = field(default_factory=Sensors)
    process_scale: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "process_scale", number(self.process_scale,
                                                         "truth.process_scale", low=0.0))

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


def from_cfg(cfg: Any, wheelbase: float) -> Truth:
    """The Truth of the Hydra group ``truth`` (None or absent: the kinematic bicycle).

    ``truth.name`` is looked up among the registered truth models (entry-point group
    ``lbo.truths``; nothing a config names is imported otherwise). Raises LboError naming the
    field for an unknown model, a bad value, a car that does not keep :class:`Car`, or axle
    distances that do not sum to the vehicle's wheelbase.
    """
    if cfg is None:
        return Truth()
    c = dict(cfg)
    name = c.pop("name", "kinematic")
    cls: type[Any] = plugins.load("truth", name, "truth.name")  # a class, Kinematic or a car
    sensor_keys = [f for f in Sensors.__dataclass_fields__]
    sensors = Sensors(**{k: c.pop(k) for k in sensor_keys if k in c})
    scale = c.pop("process_scale", 1.0)
    sensor_keys.append("process_scale")
    if cls is Kinematic:
        if c:
            raise LboError(f"truth.{next(iter(c))}: not a field of truth={name}; "
                           f"accepted: name, {', '.join(sensor_keys)}")
        return Truth(name, None, sensors, scale)
    if not dataclasses.is_dataclass(cls):
        raise LboError(f"truth.name: truth model {name!r} is registered as {cls!r}, not a "
                       "dataclass of its settings (docs/plugins.md)")
    car_keys = [f.name for f in dataclasses.fields(cls)]
    unknown = [k for k in c if k not in car_keys]
    if unknown:
        raise LboError(f"truth.{unknown[0]}: not a field of truth={name}; accepted: "
                       f"name, {', '.join(car_keys + sensor_keys)}")
    try:
        car = cast(Car, cls(**c))  # that it keeps Car's members is checked below
    except (TypeError, ValueError) as e:  # a plug-in's own check, said in lbo's one line
        raise LboError(f"truth: truth model {name!r} refused its settings ({e})") from None
    missing = [m for m in ("wheelbase", "understeer_gradient", "start", "step", "rear_slip")
               if not hasattr(car, m)]
    if missing:
        raise LboError(f"truth.name: truth model {name!r} lacks {', '.join(missing)} (a car "
                       "keeps lbo.sim.truth.Car: docs/plugins.md)")
    axles = hasattr(car, "l_f") and hasattr(car, "l_r")  # the field a user sets, if it has them
    require(abs(float(car.wheelbase) - wheelbase) < 1e-6,
            "truth.l_f + truth.l_r" if axles else f"truth={name}'s wheelbase",
            f"the vehicle's wheelbase ({wheelbase} m)", car.wheelbase)
    return Truth(name, car, sensors, scale)


def of_folder(folder: Any, wheelbase: float) -> Truth:
    """The Truth a data-set folder was drawn from, as its ``manifest.json`` records it (the
    paper's kinematic bicycle when the manifest names none, or is missing)."""
    import json
    from pathlib import Path

    manifest = Path(folder) / "manifest.json"
    if not manifest.is_file():
        return Truth()
    return from_cfg(json.loads(manifest.read_text()).get("truth"), wheelbase)
