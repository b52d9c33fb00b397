"""The report's sections on the studies beyond the paper's tables: the robust observer and the
learned peers trained as it is, the car that slips, and the observers through GNSS outages.
Each is a :class:`lbo.scoring.report.Section` that :func:`lbo.scoring.report.write` writes
after the paper's tables.
"""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import pandas as pd

from lbo.core import plots
from lbo.core.atomic import atomic_path
from lbo.filters import classical
from lbo.scoring.report import VARIABLES, crossover, md_table, present


def robust_markdown(table: pd.DataFrame, robust: str, peers: tuple[str, ...] = ()
                    ) -> list[str]:
    """The robust observer against the classical peers, per alpha, with its oracle ratio;
    ``peers``: learned observers trained as it is (KalmanNet, Split-KalmanNet), each with its
    NRMSE and its own ratio to the oracle."""
    learned = present(table, (robust, *peers))
    nr = table.pivot(index="alpha", columns="observer", values="nrmse")[
        present(table, (*learned, *classical.KINEMATIC_PEERS))]
    ratios = {name: table[table["observer"] == name].set_index("alpha")["ratio_to_oracle"]
              for name in learned}
    for name, ratio in ratios.items():
        nr[f"{name} / oracle"] = ratio
    ratio = ratios[robust]
    worst = ratio[(ratio.index >= 0.25 - 1e-9)].max()
    cross = crossover(table, robust)
    where = "never on 0..6" if cross is None else f"from alpha = {cross:.2f}"
    beside = [f"`{name}` {ratios[name][ratios[name].index >= 0.25 - 1e-9].max():.3f}"
              for name in learned if name != robust]
    trained = (f" Trained as it is, the learned peers' worst ratios: {', '.join(beside)}."
               if beside else "")
    return ["## Beyond the paper: one observer for every noise level", "",
            f"`{robust}` (`experiment=robust`) is never told alpha. NRMSE per alpha beside the "
            "EKF (R at alpha=1), the oracle EKF (told alpha), the adaptive EKF and the PCRB, "
            f"and its ratio to the oracle. Worst ratio over alpha in [0.25, 6]: {worst:.3f}. "
            f"It is below the EKF {where}.{trained}", "",
            md_table(nr.reset_index()), "", "![robust](nrmse_robust.png)", ""]


BLACK_BOXES = ("cnn", "lstm")
"""The models of a car-that-slips table's black-box peers (``experiment=dynamic_blackbox``)."""
LEARNED_PEERS = ("kalmannet", "split_kalmannet")
"""The models of its learned peers of the literature (``reproduce``'s ``dynamic_peers``)."""


def _model(observer: str) -> str:
    """The model of a learned observer's name (``kalmannet-N400`` -> ``kalmannet``)."""
    return observer.rsplit("-N", 1)[0]


def dynamic_summary(table: pd.DataFrame, low: float = 0.25, high: float = 6.0) -> dict:
    """The observer that learns the model error (the learned one that is neither a black-box
    CNN or LSTM nor a learned peer, :data:`LEARNED_PEERS`) in a car-that-slips table, against
    its peers over alpha in [low, high]: its name, the black boxes' and the learned peers'
    names, each learned peer's range of NRMSE over the dynamic oracle's (``peers_vs_dynamic``),
    and the ranges of its NRMSE over the kinematic oracle's, over the
    dynamic oracle's, over the adaptive EKF's and over the kinematic EKF tuned in hindsight
    (``oracle_tuned``; None without it), and of the dynamic oracle's over the kinematic one's,
    each ``(min, max)``."""
    learned = [o for o in dict.fromkeys(table["observer"]) if o not in classical.NAMES]
    boxes = [o for o in learned if _model(o) in BLACK_BOXES]
    peers = [o for o in learned if _model(o) in LEARNED_PEERS]
    main = [o for o in learned if o not in boxes and o not in peers]
    if len(main) != 1:
        raise ValueError(f"expected one observer besides the black boxes and the learned "
                         f"peers, got {main}")
    nr = table.pivot_table(index="alpha", columns="observer", values="nrmse")
    nr = nr[(nr.index >= low - 1e-9) & (nr.index <= high + 1e-9)]
    name = main[0]

    def span(a: str, b: str) -> tuple[float, float]:
        r = nr[a] / nr[b]
        return float(r.min()), float(r.max())

    return {"observer": name, "black_boxes": boxes, "peers": peers,
            "peers_vs_dynamic": {p: span(p, "oracle_dynamic") for p in peers},
            "vs_oracle": span(name, "oracle"),
            "vs_dynamic": span(name, "oracle_dynamic"), "vs_adaptive": span(name, "adaptive"),
            "vs_tuned": span(name, "oracle_tuned") if "oracle_tuned" in nr else None,
            "dynamic_vs_oracle": span("oracle_dynamic", "oracle")}


def dynamic_markdown(key: str, table: pd.DataFrame) -> list[str]:
    """The section of a car that slips (``data=<key>``): NRMSE per alpha against the kinematic
    EKFs and the dynamic oracle, the ratios, RMSE per variable at alpha 1, 3 and 6."""
    s = dynamic_summary(table)
    name = s["observer"]
    peers = present(table, (name, *s["black_boxes"], *s["peers"], *classical.DYNAMIC_PEERS))
    nr = table.pivot_table(index="alpha", columns="observer", values="nrmse")[peers]
    nr = nr[nr.index.isin([0.25, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0])]
    nr[f"{name} / oracle"] = nr[name] / nr["oracle"]
    for learned in (name, *s["peers"]):
        nr[f"{learned} / oracle_dynamic"] = nr[learned] / nr["oracle_dynamic"]
    if s["vs_tuned"] is not None:
        nr[f"{name} / oracle_tuned"] = nr[name] / nr["oracle_tuned"]
    rows = []
    for alpha in (1.0, 3.0, 6.0):
        at = table[np.isclose(table["alpha"], alpha)].set_index("observer")
        for obs in peers:
            if obs in at.index:
                rows.append({"alpha": alpha, "observer": obs,
                             **{f"{v} ({u})": float(cast(float, at.loc[obs, f"rmse_{v}"]) * k)
                                for v, u, k in VARIABLES}})
    lo, hi = s["vs_oracle"]
    dlo, dhi = s["dynamic_vs_oracle"]
    return [f"## Where learning beats the model: `data={key}`", "",
            f"`{name}` (`experiment=dynamic`) is never told alpha or the car. Over alpha in "
            f"[0.25, 6] its NRMSE is {1 - hi:.0%} to {1 - lo:.0%} below the kinematic oracle "
            f"EKF's (the EKF on the car, `oracle_dynamic`, is {1 - dhi:.0%} to {1 - dlo:.0%} "
            f"below it), {s['vs_dynamic'][0]:.2f} to {s['vs_dynamic'][1]:.2f} times the "
            f"dynamic oracle's, and {s['vs_adaptive'][0]:.2f} to {s['vs_adaptive'][1]:.2f} "
            "times the adaptive EKF's"
            + (f", and {s['vs_tuned'][0]:.2f} to {s['vs_tuned'][1]:.2f} times the kinematic "
               "EKF's with Q tuned in hindsight per alpha (`oracle_tuned`), the fair kinematic "
               "peer." if s["vs_tuned"] is not None else ".")
            + (" Black-box peers trained on the same data (`experiment=dynamic_blackbox`): "
               f"{', '.join(f'`{b}`' for b in s['black_boxes'])}." if s["black_boxes"] else "")
            + (" The learned peers around the single-track body, trained as it is, over the "
               "dynamic oracle's: " + ", ".join(f"`{p}` {lo:.2f} to {hi:.2f}" for p, (lo, hi)
                                                  in s["peers_vs_dynamic"].items()) + "."
               if s["peers"] else ""),
            "",
            md_table(nr.reset_index()), "", "RMSE per variable (psi in mrad):", "",
            md_table(pd.DataFrame(rows)), "", f"![{key}](nrmse_{key}.png)", ""]


def lateral_markdown(scores: pd.DataFrame) -> list[str]:
    """The side slip beta (deg), v_y and r of each estimator at alpha 1, 3 and 6, and beta's
    NEES where the estimator gives its variance."""
    at = scores[scores["alpha"].isin([1.0, 3.0, 6.0])]
    shown = pd.DataFrame({"observer": at["observer"], "alpha": at["alpha"],
                          "beta (deg)": np.rad2deg(at["rmse_beta"]), "v_y (m/s)": at["rmse_vy"],
                          "r (rad/s)": at["rmse_r"], "beta NEES": at["nees_beta"]})
    return ["The states no sensor gives, RMSE over the scored rows (a learned observer's: the "
            "v_y and r its single-track body carries, its variances made of the body's error "
            "on the validation set; `lateral.csv` of `lbo.evaluate`), and beta's NEES (1 for "
            "an honest variance; nan: none given):", "", md_table(shown), ""]


@dataclass(frozen=True)
class Robust:
    """The robust observer ``name`` of the score table against its classical peers
    (:data:`lbo.filters.classical.KINEMATIC_PEERS`) and the learned ``peers`` trained as it
    is: ``nrmse_robust.png``."""

    name: str
    peers: tuple[str, ...] = ()
    figure: str = "nrmse_robust.png"

    @property
    def headline(self) -> tuple[str, ...]:
        return (self.name,)

    def markdown(self, table: pd.DataFrame) -> list[str]:
        return robust_markdown(table, self.name, self.peers)

    def write(self, folder: Path, table: pd.DataFrame) -> list[Path]:
        shown = [*present(table, (self.name, *self.peers)),
                 *present(table, classical.KINEMATIC_PEERS)]
        return [plots.save(plots.nrmse_curves(
            table, f"{self.name}, never told alpha, against the classical peers",
            observers=shown), folder / self.figure)]


@dataclass(frozen=True)
class Dynamic:
    """The car-that-slips study on data set ``key``: its score ``table`` (one learned
    observer, black boxes maybe, and :data:`lbo.filters.classical.DYNAMIC_PEERS`):
    ``<key>.csv`` and ``nrmse_<key>.png``; with ``lateral`` (:func:`lbo.scoring.lateral.table`
    rows), the states no sensor gives too: ``lateral_<key>.csv``."""

    key: str
    table: pd.DataFrame
    _: KW_ONLY
    headline: tuple[str, ...] = ()
    lateral: pd.DataFrame | None = None

    @property
    def figure(self) -> str:
        return f"nrmse_{self.key}.png"

    def markdown(self, table: pd.DataFrame) -> list[str]:
        return [*dynamic_markdown(self.key, self.table), *([] if self.lateral is None else
                                                          lateral_markdown(self.lateral))]

    def write(self, folder: Path, table: pd.DataFrame) -> list[Path]:
        with atomic_path(folder / f"{self.key}.csv") as tmp:
            self.table.to_csv(tmp, index=False)
        s = dynamic_summary(self.table)
        lateral = [] if self.lateral is None else [folder / f"lateral_{self.key}.csv"]
        if lateral:
            with atomic_path(lateral[0]) as tmp:
                cast(pd.DataFrame, self.lateral).to_csv(tmp, index=False)
        return [folder / f"{self.key}.csv", *lateral, plots.save(plots.nrmse_curves(
            self.table, f"a car that slips (data={self.key}): {s['observer']} against the "
            "kinematic EKFs and the EKF told the car",
            observers=present(self.table, (s["observer"], *s["black_boxes"], *s["peers"],
                                            *classical.DYNAMIC_PEERS))),
            folder / self.figure)]


@dataclass(frozen=True)
class Outages:
    """Every observer through GNSS outages cut into the test grid (``table``:
    :func:`lbo.scoring.outages.score_grid`'s rows, outages of ``length_s`` every ``every_s``
    seconds): ``outages.csv`` and ``outages_end.png``, the error at an outage's end per
    alpha."""

    table: pd.DataFrame
    _: KW_ONLY
    length_s: float
    every_s: float
    headline: tuple[str, ...] = ()
    figure: str = "outages_end.png"

    @classmethod
    def of(cls, test: Path, outages: Any, cfg: Any, classical_names: list[str],
           learned: dict[str, str]) -> Outages:
        """The section for the test file ``test``: the ``learned`` observers (label ->
        checkpoint) and ``classical_names`` through ``outages``
        (:func:`lbo.scoring.outages.grid_table`), the car of the composed config ``cfg``."""
        from lbo.scoring import outages as outage
        from lbo.scoring.grid import load_test
        from lbo.sim.noise import Noise
        from lbo.sim.vehicle import Vehicle
        from lbo.tracking.artifacts import load_net

        vehicle, noise = Vehicle.from_cfg(cfg.vehicle), Noise.from_cfg(cfg.noise)
        arr = load_test(test)
        spans = outage.grid_windows(arr, outages, vehicle.dt)
        nets = {label: load_net(path)[0] for label, path in learned.items()}
        print(f"    through GNSS outages of {outages.length_s:g} s every {outages.every_s:g} "
              f"s: {len(spans)} in the test grid", flush=True)
        return cls(outage.grid_table(arr, spans, vehicle, noise, classical_names, nets),
                   length_s=outages.length_s, every_s=outages.every_s)

    def markdown(self, table: pd.DataFrame) -> list[str]:
        t = self.table[self.table["alpha"].isin([1.0, 3.0, 6.0])]
        end = t.pivot(index="estimator", columns="alpha", values="end_m")
        nees = t.pivot(index="estimator", columns="alpha", values="nees")
        rows = pd.DataFrame({"observer": end.index, **{
            f"end (m), alpha {a:g}": end[a].to_numpy() for a in end.columns}, **{
            f"NEES, alpha {a:g}": nees[a].to_numpy() for a in nees.columns}})
        order = list(dict.fromkeys(self.table["estimator"]))
        rows = rows.set_index("observer").loc[order].reset_index()
        band = self.table.dropna(subset=["nees_low"]).drop_duplicates("alpha")
        inside = (f" The 95% band of a level's mean NEES: {band['nees_low'].min():.2f} to "
                  f"{band['nees_high'].max():.2f}." if len(band) else "")
        return ["## Through GNSS outages", "",
                f"Every test trajectory's fixes blanked for {self.length_s:g} s, one outage "
                f"every {self.every_s:g} s from its first fix while the car moves "
                f"({int(t['outages'].max()) if len(t) else 0} outages per level): the "
                "position error at an outage's end, and the NEES over the outages' rows "
                f"(3 for an honest covariance; none where an observer gives none).{inside}", "",
                md_table(rows), "", f"![outages]({self.figure})", ""]

    def write(self, folder: Path, table: pd.DataFrame) -> list[Path]:
        with atomic_path(folder / "outages.csv") as tmp:
            self.table.to_csv(tmp, index=False)
        curves = self.table.rename(columns={"estimator": "observer", "end_m": "nrmse"})
        return [folder / "outages.csv", plots.save(plots.nrmse_curves(
            curves, f"through GNSS outages of {self.length_s:g} s: the error at their end",
            ylabel="position error at an outage's end (m)", reference=None),
            folder / self.figure)]
