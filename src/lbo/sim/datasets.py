"""The paper's three data sets from one config: checked, hashed, cached and written atomically."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from lbo.core.angles import wrap_angle
from lbo.core.atomic import data_lock, remove_stale_temps, write_text
from lbo.core.checks import integer, number, positive, require
from lbo.core.errors import LboError
from lbo.sim import clothoid, dynamic, schema
from lbo.sim.columns import LATERAL
from lbo.sim.friction import G, Grid, accelerations, generate_train
from lbo.sim.manoeuvres import MANOEUVRES, validation_path
from lbo.sim.noise import Noise, check_alpha
from lbo.sim.pursuit import drive, smooth_noise
from lbo.sim.stopgo import generate_stop_and_go
from lbo.sim.truth import Truth
from lbo.sim.truth import of_config as truth_of_config
from lbo.sim.vehicle import Vehicle, measure

# Bump when a generator changes what it writes, so old caches are not reused.
DATAGEN_VERSION = 1
SETS = ("train", "val", "test")
DS = 0.1  # path sampling (m)
FIGURES = ("friction_circle.png", "test_manoeuvres.png")
MANIFEST = schema.MANIFEST
# every file build() and figures() write into a data-set folder
FILES = (*(f"{n}.parquet" for n in SETS), MANIFEST, *FIGURES)


@dataclass(frozen=True, kw_only=True)
class Spec:
    """A checked data config: everything the generators need, nothing from Hydra."""

    name: str
    root: Path
    seed: int
    vehicle: Vehicle
    noise: Noise
    train: dict
    val: dict
    test: dict
    digest: str
    truth: Truth = Truth()

    @property
    def folder(self) -> Path:
        return self.root / f"{self.name}-{self.digest}"

    @property
    def motion_noise(self) -> Noise:
        """The noise preset with the truth's own process noise (``car.process_scale``)."""
        if self.truth.process_scale == 1.0:
            return self.noise
        return Noise(tuple(self.truth.process_sigma(self.noise)), self.noise.measurement_sigma,
                     self.noise.name)

    @property
    def alphas(self) -> np.ndarray:
        t = self.test
        n = int(round(t["alpha_max"] / t["alpha_step"]))
        return np.round(np.arange(n + 1) * t["alpha_step"], 10)


SIDESLIP = {"sideslip": "the real side-slip run",
            "sideslip_sim": "simulated runs of the side-slip run's kind"}
"""``data.name`` of the side-slip observers' data sets, which only they read."""


def refuse_sideslip(cfg: DictConfig) -> None:
    """``data=sideslip`` and ``sideslip_sim`` are the side-slip observers' (``model=slip_gru``,
    ``slip_filter``):
    no pose observer, data set or test grid is made of them. One line naming ``data``."""
    name = cfg.data.get("name") if cfg.get("data") is not None else None
    if name in SIDESLIP:
        raise LboError(f"data: data={name} is {SIDESLIP[name]}, which the side-slip observers "
                       f"alone read (python -m lbo.train model=slip_gru|slip_filter "
                       f"data={name}); expected a "
                       "simulated data set (smoke, quick, paper, robust, dynamic) or logs")


def spec_from_cfg(cfg: DictConfig) -> Spec:
    """Check a composed config (groups ``data``, ``vehicle``, ``noise``) and build the Spec.

    Raises LboError with one line naming the first bad field.
    """
    refuse_sideslip(cfg)
    vehicle = Vehicle.from_cfg(cfg.vehicle)
    noise = Noise.from_cfg(cfg.noise)
    truth = truth_of_config(cfg, vehicle.wheelbase)
    d = cfg.data
    integer(d.seed, "data.seed", 0)
    # each block is a mapping (a DictConfig), so its container is a dict
    tr = cast(dict, OmegaConf.to_container(d.train, resolve=True))
    for key in ("n_traj", "candidates", "grid"):
        positive(tr, key, "data.train", integer=True)
    for key in ("duration", "radius_g", "jerk"):
        positive(tr, key, "data.train")
    require(tr["duration"] >= 2 * vehicle.dt, "data.train.duration",
            f"at least two steps ({2 * vehicle.dt} s)", tr["duration"])
    hold = tr["hold"]
    require(len(hold) == 2 and 0 < hold[0] <= hold[1], "data.train.hold",
            "[min, max] seconds with 0 < min <= max", hold)
    check_alpha(tr["alpha"], "data.train.alpha")
    share = tr.get("stop_and_go", 0.0)
    number(share, "data.train.stop_and_go", low=0.0, high=1.0,
           form="a share of the trajectories in [0, 1]")
    va = cast(dict, OmegaConf.to_container(d.val, resolve=True))
    for key in ("steps", "run_in"):
        positive(va, key, "data.val", integer=True)
    for key in ("length", "amplitude", "period"):
        positive(va, key, "data.val")
    require(0 <= va["speed_variation"] < 1, "data.val.speed_variation", "in [0, 1)",
            va["speed_variation"])
    check_alpha(va["alpha"], "data.val.alpha")
    te = cast(dict, OmegaConf.to_container(d.test, resolve=True))
    positive(te, "run_in", "data.test", integer=True)
    require(te["run_in"] >= 80 and va["run_in"] >= 80, "data.test.run_in and data.val.run_in",
            "at least 80 steps, so every window N <= 80 is scored on the same points",
            (te["run_in"], va["run_in"]))
    positive(te, "alpha_step", "data.test")
    check_alpha(te["alpha_max"], "data.test.alpha_max")
    require(0 <= te["speed_variation"] < 1, "data.test.speed_variation", "in [0, 1)",
            te["speed_variation"])
    for part, block in (("val", va), ("test", te)):
        if "speed_factor" in block:
            number(block["speed_factor"], f"data.{part}.speed_factor", low=0.0, low_open=True)
        if block.get("max_lateral_g") is not None:
            number(block["max_lateral_g"], f"data.{part}.max_lateral_g", low=0.0, low_open=True)
    names = te["manoeuvres"]
    require(len(names) > 0, "data.test.manoeuvres", "a non-empty list of manoeuvre names", names)
    for n in names:
        require(n in MANOEUVRES, "data.test.manoeuvres",
                f"names from {sorted(MANOEUVRES)}", n)
    require(len(set(names)) == len(names), "data.test.manoeuvres", "names without repeats", names)

    hashed = {"version": DATAGEN_VERSION, "seed": d.seed, "train": tr, "val": va, "test": te,
              "vehicle": vehicle.__dict__,
              "noise": [noise.process_sigma, noise.measurement_sigma]}
    if not truth.default:  # the paper's sets keep the folder names they always had
        hashed["truth"] = truth.to_dict()
    digest = hashlib.sha256(json.dumps(hashed, sort_keys=True).encode()).hexdigest()[:12]
    return Spec(name=str(d.name), root=Path(d.root), seed=int(d.seed), vehicle=vehicle,
                noise=noise, train=tr, val=va, test=te, digest=digest, truth=truth)


def _rng(spec: Spec, *key: int) -> np.random.Generator:
    return np.random.default_rng([spec.seed, *key])


def _sensed(spec: Spec, out: dict[str, np.ndarray], alpha: float, key: int
            ) -> dict[str, np.ndarray]:
    """The truth model's share of a training set: B trajectories (B, T, ...) driven by the
    dynamic car instead of the kinematic bicycle (the same inputs, fresh process noise), and
    the sensors' errors (GNSS drift on the measurements, logged inputs). The paper's truth
    returns ``out`` untouched."""
    truth, v = spec.truth, spec.vehicle
    if truth.default:
        return out
    z, u, m = out["z"], out["u"], out["m"]
    if truth.car is not None:
        rng = _rng(spec, key)
        z = dynamic.simulate(z[:, 0], u, v.dt, truth.car, spec.motion_noise.process_sigma,
                             rng, truth.lateral_sigma)[..., :3]
        z[..., 2] = wrap_angle(z[..., 2])
        m = measure(z, spec.noise.meas(alpha), rng)
    m = m + truth.sensors.drift(z.shape[:2], v.dt, alpha, _rng(spec, key, 1))
    m[..., 2] = wrap_angle(m[..., 2])
    return {"z": z, "u": truth.sensors.logged_inputs(u), "m": m}


def make_train(spec: Spec) -> pd.DataFrame:
    """Friction-circle trajectories, the last ``stop_and_go`` share of them replaced by
    stop-and-go ones (:mod:`lbo.sim.stopgo`) when the config asks for it."""
    tr, v = spec.train, spec.vehicle
    n_steps = int(round(tr["duration"] / v.dt))
    b = tr["n_traj"]
    n_stop = int(round(tr.get("stop_and_go", 0.0) * b))
    out = generate_train(b - n_stop, n_steps, v, spec.motion_noise, _rng(spec, 1),
                         radius=tr["radius_g"] * G, grid=tr["grid"], hold=tuple(tr["hold"]),
                         jerk=tr["jerk"], candidates=tr["candidates"], alpha=tr["alpha"],
                         understeer=_understeer(spec))
    out = _sensed(spec, out, tr["alpha"], 7)
    if n_stop:
        stops = generate_stop_and_go(n_stop, n_steps, v, spec.motion_noise, _rng(spec, 6),
                                     alpha=tr["alpha"])
        stops = _sensed(spec, stops, tr["alpha"], 8)
        out = {key: np.concatenate([out[key], stops[key]]) for key in ("z", "u", "m")}
    traj = np.repeat(np.arange(b), n_steps)
    k = np.tile(np.arange(n_steps), b)
    return schema.frame(traj, k, v.dt, out["z"].reshape(-1, 3), out["u"].reshape(-1, 2),
                        out["m"].reshape(-1, 3))


def _understeer(spec: Spec) -> float:
    car = spec.truth.car
    return 0.0 if car is None else car.understeer_gradient


def drive_paths(spec: Spec, segments: list, steps: np.ndarray, shapes: np.ndarray, run_in: int,
                variation: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Drive G clothoid chains with pure pursuit. steps, shapes: (G,), (G, 2)."""
    v = spec.vehicle
    lengths = np.array([clothoid.path_length(s) for s in segments])
    t_max = run_in + int(steps.max())
    # linear speed shape over the scored steps, mean 1, held at its start value in the run-in
    frac = np.clip((np.arange(t_max)[None, :] - run_in) / steps[:, None], 0.0, 1.0)
    shape = shapes / shapes.mean(axis=1, keepdims=True)
    v_mean = lengths / (steps * v.dt)
    speed = v_mean[:, None] * (shape[:, :1] + (shape[:, 1:] - shape[:, :1]) * frac)
    speed *= 1 + variation * smooth_noise(len(segments), t_max, v.dt, rng)
    speed = np.clip(speed, v.v_min, v.v_max)
    lead = run_in * v.dt * speed[:, :run_in].mean(axis=1)
    paths = [clothoid.sample(s, DS, lead_in=li, tail=0.6 * L + 60)
             for s, li, L in zip(segments, lead, lengths)]
    return drive(paths, speed, v, np.asarray(spec.motion_noise.process_sigma), rng, ds=DS,
                 car=spec.truth.car, lateral_sigma=spec.truth.lateral_sigma)


def _scored_frame(spec: Spec, z: np.ndarray, u: np.ndarray, n_real: np.ndarray, run_in: int,
                  alphas: np.ndarray, key: int, lateral: np.ndarray) -> pd.DataFrame:
    """Rows for every alpha level (independent seeded noise per level), alpha-major.

    z, u, lateral: (G, T, 3|2|2) padded; n_real: (G,) real steps per trajectory. A car that
    slips adds its true lateral states (:data:`lbo.sim.columns.LATERAL`) to each row.
    """
    g, t_max = z.shape[:2]
    real = np.arange(t_max)[None, :] < n_real[:, None]
    traj, k = np.nonzero(real)
    zs, us = z[real], spec.truth.sensors.logged_inputs(u[real])
    states = ({} if spec.truth.car is None else
              {name: lateral[real][:, i] for i, name in enumerate(LATERAL)})
    frames = []
    for i, a in enumerate(alphas):
        m = measure(zs, spec.noise.meas(a), _rng(spec, key, i))
        if spec.truth.sensors.gnss_sigma > 0:  # drift of each padded trajectory, real rows
            m += spec.truth.sensors.drift((g, t_max), spec.vehicle.dt, a,
                                          _rng(spec, key, i, 1))[real]
        m[:, 2] = wrap_angle(m[:, 2])
        frames.append(schema.frame(traj, k, spec.vehicle.dt, zs, us, m,
                                   alpha=np.full(len(k), a), scored=k >= run_in, **states))
    return pd.concat(frames, ignore_index=True)


def slower_steps(steps: np.ndarray, block: dict) -> np.ndarray:
    """Scored steps per path at ``speed_factor`` times the paths' speeds (the same paths,
    driven to their ends): the paper's counts at the default 1."""
    factor = block.get("speed_factor", 1.0)
    return steps if factor == 1.0 else np.round(steps / factor).astype(np.int64)


def peak_lateral_g(z: np.ndarray, u: np.ndarray, n_real: np.ndarray, dt: float) -> np.ndarray:
    """(G,) largest lateral acceleration (in g) of each driven path: speed times yaw rate,
    the yaw rate over 0.2 s so that the process noise's jitter does not count.
    z, u: (G, T, 3|2) padded; n_real: (G,) real steps."""
    lag = max(1, int(round(0.2 / dt)))
    psi = np.unwrap(z[..., 2], axis=1)
    rate = (psi[:, lag:] - psi[:, :-lag]) / (lag * dt)
    a = np.abs(u[:, :-lag, 0] * rate) / G
    real = np.arange(a.shape[1])[None, :] < (n_real - lag)[:, None]
    return np.where(real, a, 0.0).max(axis=1)


def drive_within_grip(spec: Spec, segments: list, steps: np.ndarray, shapes: np.ndarray,
                      run_in: int, block: dict, new_rng: Callable[[], np.random.Generator]
                      ) -> tuple[dict[str, np.ndarray], np.ndarray, np.random.Generator]:
    """Drive the paths (:func:`drive_paths`); with ``block["max_lateral_g"]`` set, a path whose
    car corners harder than that is driven again slower, by the factor that brings it there
    (lateral acceleration goes as speed squared), so no manoeuvre asks more of the tyres than
    the training set does. Each drive draws from a fresh ``new_rng()``. Returns the drive, the
    scored steps per path (G,) and the generator of the last drive."""
    cap = block.get("max_lateral_g")
    for _ in range(4):
        rng = new_rng()
        out = drive_paths(spec, segments, steps, shapes, run_in, block["speed_variation"], rng)
        if cap is None:
            break
        peak = peak_lateral_g(out["z"], out["u"], run_in + steps, spec.vehicle.dt)
        over = peak > cap
        if not over.any():
            break
        factor = np.where(over, 0.97 * np.sqrt(cap / np.maximum(peak, 1e-9)), 1.0)
        steps = np.ceil(steps / factor).astype(np.int64)
    return out, steps, rng


def make_val(spec: Spec) -> pd.DataFrame:
    va = spec.val
    seg = validation_path(va["length"], va["amplitude"], va["period"])
    steps = slower_steps(np.array([va["steps"]]), va)
    out, steps, _ = drive_within_grip(spec, [seg], steps, np.ones((1, 2)), va["run_in"], va,
                                      lambda: _rng(spec, 2))
    return _scored_frame(spec, out["z"], out["u"], va["run_in"] + steps,
                         va["run_in"], np.array([va["alpha"]]), 3, out["lateral"])


def make_test(spec: Spec) -> pd.DataFrame:
    te = spec.test
    man = [MANOEUVRES[n] for n in te["manoeuvres"]]
    steps = slower_steps(np.array([m.steps for m in man]), te)
    out, steps, _ = drive_within_grip(spec, [m.build() for m in man], steps,
                                      np.array([m.speed_shape for m in man]), te["run_in"], te,
                                      lambda: _rng(spec, 4))
    return _scored_frame(spec, out["z"], out["u"], te["run_in"] + steps, te["run_in"],
                         spec.alphas, 5, out["lateral"])


MAKERS = {"train": make_train, "val": make_val, "test": make_test}


def summary(spec: Spec, sets: dict[str, pd.DataFrame]) -> dict[str, Any]:
    """Rows per set, friction-circle coverage of the training set, speed and heading ranges
    (``(min, max)`` each)."""
    tr = sets["train"]
    acc = train_accelerations(spec, tr)
    grid = Grid(spec.train["radius_g"] * G, spec.train["grid"])
    out: dict[str, Any] = {f"rows_{n}": len(df) for n, df in sets.items()}
    out["scored_val"] = int(sets["val"]["scored"].sum())
    out["scored_test_per_alpha"] = int(sets["test"]["scored"].sum() // len(spec.alphas))
    out["scored_test"] = int(sets["test"]["scored"].sum())
    out["coverage"] = grid.coverage(acc)
    for n, df in sets.items():
        out[f"V_{n}"] = (float(df["V"].min()), float(df["V"].max()))
        out[f"psi_{n}"] = (float(df["psi"].min()), float(df["psi"].max()))
    return out


def train_accelerations(spec: Spec, train: pd.DataFrame) -> np.ndarray:
    """(S, 2) vehicle-frame accelerations (a_lon, a_lat) of the training set."""
    n = spec.train["n_traj"]
    V = train["V"].to_numpy().reshape(n, -1)
    delta = train["delta"].to_numpy().reshape(n, -1)
    return accelerations(V, delta, spec.vehicle.dt, spec.vehicle.wheelbase,
                         _understeer(spec)).reshape(-1, 2)


def figures(spec: Spec, sets: dict[str, pd.DataFrame], folder: Path) -> list[Path]:
    """friction_circle.png and test_manoeuvres.png in ``folder``."""
    from lbo.core import plots

    grid = Grid(spec.train["radius_g"] * G, spec.train["grid"])
    acc = train_accelerations(spec, sets["train"])
    tr = sets["train"]
    fc = plots.friction_circle(acc, grid.radius, grid.edges, tr["V"].to_numpy(),
                               tr["psi"].to_numpy(), grid.coverage(acc))
    te = sets["test"]
    one = te[te["alpha"] == spec.alphas[0]]
    xy = {name: one.loc[one["traj"] == i, ["x", "y"]].to_numpy()
          for i, name in enumerate(spec.test["manoeuvres"])}
    tm = plots.paths(xy, scored_from=spec.test["run_in"])
    return [plots.save(fc, folder / FIGURES[0]), plots.save(tm, folder / FIGURES[1])]


def build(spec: Spec, progress: bool = True) -> tuple[Path, dict[str, pd.DataFrame], bool]:
    """Generate (or reuse) the three sets under ``spec.folder``.

    Returns the folder, the frames, and whether they came from the cache. Files are written
    atomically; a set is reused only when its Parquet file is the one this cache wrote
    (:func:`lbo.sim.schema.cached_set`): one cut short or replaced is said in one line and
    generated again (the generators are seeded: the same file comes back).
    """
    with data_lock(spec.folder):
        stale = remove_stale_temps(spec.folder, FILES)
        if stale:
            print(f"removed {len(stale)} temp file(s) a killed run left in {spec.folder}: "
                  f"{', '.join(p.name for p in stale)}")
        return _build(spec, spec.folder, progress)


def _build(spec: Spec, folder: Path, progress: bool
           ) -> tuple[Path, dict[str, pd.DataFrame], bool]:
    paths = {n: folder / f"{n}.parquet" for n in SETS}
    recorded = _recorded_files(folder / MANIFEST)
    sets: dict[str, pd.DataFrame] = {}
    files: dict[str, dict] = {}  # the fingerprints the manifest will record
    cached = True
    for name in SETS:
        path = paths[name]
        if path.is_file():
            df, problem = schema.cached_set(path, recorded.get(path.name), name)
            if problem is None:
                sets[name] = cast(pd.DataFrame, df)  # cached_set gives a set where no problem
                # checked against the record above; an older cache's file is read now
                files[path.name] = recorded.get(path.name) or schema.fingerprint(path)
                continue
            print(f"{path}: {problem}; generating it again", flush=True)
        elif progress:
            print(f"generating {name} set ...", flush=True)
        cached = False
        sets[name] = MAKERS[name](spec)
        schema.write_set(sets[name], path)
        files[path.name] = schema.fingerprint(path)
    if files != recorded:  # a new cache, one written before lbo recorded its files, or a repair
        text = json.dumps({"name": spec.name, "digest": spec.digest, "seed": spec.seed,
                           "version": DATAGEN_VERSION, "vehicle": spec.vehicle.__dict__,
                           **({} if spec.truth.default else {"truth": spec.truth.to_dict()}),
                           "noise": {"name": spec.noise.name,
                                     "process_sigma": spec.noise.process_sigma,
                                     "measurement_sigma": spec.noise.measurement_sigma},
                           "train": spec.train, "val": spec.val, "test": spec.test,
                           "alphas": spec.alphas.tolist(),
                           "test_trajectories": spec.test["manoeuvres"],
                           "files": files}, indent=1)
        write_text(folder / MANIFEST, text)
    return folder, sets, cached


def _recorded_files(manifest: Path) -> dict[str, dict]:
    """The fingerprints of the sets a data-set folder's manifest records; none where it
    records none (a cache written before lbo did) or cannot be read (it is written again)."""
    try:
        files = json.loads(manifest.read_text()).get("files")
    except (OSError, ValueError, AttributeError):
        return {}
    return files if isinstance(files, dict) else {}
