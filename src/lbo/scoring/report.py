"""The paper's tables and figures from score tables: arrays and frames in, files out.

Nothing here trains or talks to MLflow; :mod:`lbo.reproduce` gathers the tables and calls
:func:`write`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, cast

import numpy as np
import pandas as pd

from lbo.core import plots
from lbo.core.atomic import atomic_path, write_text
from lbo.filters import classical
from lbo.scoring.metrics import PAPER_REFERENCE, nrmse

# The paper's Tables I and II (RMSE; psi in rad; the EKF at 1 is E_ref), its reading of Fig. 5.
PAPER_RMSE = {
    1.0: {"ekf": PAPER_REFERENCE, "cnn": (0.28, 0.23, 11e-3), "lstm": (0.65, 0.90, 13e-3)},
    6.0: {"ekf": (1.56, 1.88, 26e-3), "cnn": (0.91, 0.89, 20e-3), "lstm": (0.98, 1.10, 19e-3)},
}
PAPER_BEST_WINDOW = {"cnn": 60, "lstm": 80}
PAPER_CROSSOVER = {"cnn": 2.0, "lstm": 3.0}
VARIABLES = (("x", "m", 1.0), ("y", "m", 1.0), ("psi", "mrad", 1e3))


def learned_names(table: pd.DataFrame, model: str) -> list[str]:
    """Observer names of one architecture (``cnn-N20``, ...), sorted by window."""
    names = {o for o in table["observer"] if o.startswith(f"{model}-N")}
    return sorted(names, key=lambda o: int(o.split("-N")[1]))


def best_window(table: pd.DataFrame, model: str) -> str | None:
    """The architecture's observer with the lowest NRMSE averaged over every alpha; one with
    no score (NaN, or no row) at an alpha that another has is ranked last."""
    names = learned_names(table, model)
    if not names:
        return None
    grid = table[table["observer"].isin(names)].pivot_table(
        index="observer", columns="alpha", values="nrmse", dropna=False)
    mean = grid.reindex(names).mean(axis=1, skipna=False).fillna(np.inf)
    return str(mean.idxmin())


def crossover(table: pd.DataFrame, observer: str, baseline: str = "ekf") -> float | None:
    """Smallest alpha from which ``observer``'s NRMSE is below ``baseline``'s, interpolated
    linearly between grid levels; None if it never is, 0 if it always is."""
    a = table[table["observer"] == observer].set_index("alpha")["nrmse"]
    b = table[table["observer"] == baseline].set_index("alpha")["nrmse"]
    diff = (a - b).dropna().sort_index()
    if diff.empty:  # nothing to compare: never shown below
        return None
    below = (diff < 0).to_numpy()
    if below.all():
        return 0.0
    last_above = np.flatnonzero(~below)[-1]
    if last_above == len(diff) - 1:
        return None
    x0, x1 = diff.index[last_above], diff.index[last_above + 1]
    y0, y1 = diff.iloc[last_above], diff.iloc[last_above + 1]
    return float(x0 + (x1 - x0) * y0 / (y0 - y1))


def rmse_table(table: pd.DataFrame, alpha: float, cnn: str | None,
               lstm: str | None) -> pd.DataFrame:
    """Table I (alpha=1) or II (alpha=6): rows x, y, psi; ours beside the paper's.

    Columns: ``variable, unit, ekf, ekf_paper, cnn, cnn_paper, lstm, lstm_paper`` (psi in
    mrad, as in the paper), plus ``cnn_observer`` and ``lstm_observer`` naming the windows.
    """
    rows = []
    at = table[np.isclose(table["alpha"], alpha)].set_index("observer")
    for i, (var, unit, scale) in enumerate(VARIABLES):
        row: dict[str, Any] = {"variable": var, "unit": unit}
        for key, name in (("ekf", "ekf"), ("cnn", cnn), ("lstm", lstm)):
            # one row per observer: a number; name is one of them where it is in the index
            ours = (cast(float, at.loc[cast(str, name), f"rmse_{var}"]) * scale
                    if name in at.index else np.nan)
            row[key] = float(ours)
            paper = PAPER_RMSE.get(alpha, {}).get(key, (np.nan,) * 3)[i]
            row[f"{key}_paper"] = round(paper * scale, 6)
        rows.append(row)
    out = pd.DataFrame(rows)
    out["cnn_observer"], out["lstm_observer"] = cnn, lstm
    return out


def with_oracle_ratio(table: pd.DataFrame) -> pd.DataFrame:
    """``table`` plus ``ratio_to_oracle``: each row's NRMSE over the oracle EKF's at its alpha.

    NaN where there is no oracle row, or where the oracle's NRMSE is 0 (alpha = 0).
    """
    out = table.copy()
    if "oracle" not in set(table["observer"]):
        out["ratio_to_oracle"] = np.nan
        return out
    oracle = table[table["observer"] == "oracle"].groupby("alpha")["nrmse"].first()
    floor = out["alpha"].map(oracle)
    out["ratio_to_oracle"] = (out["nrmse"] / floor.where(floor > 1e-9)).astype(float)
    return out


def crossover_markdown(table: pd.DataFrame) -> list[str]:
    """Where each learned observer crosses the EKF."""
    learned = [o for o in dict.fromkeys(table["observer"])
               if o not in classical.NAMES]
    out = ["## Where each learned observer crosses the EKF", "",
           "| observer | training noise | below the EKF from alpha |", "|---|---|---|"]
    for name in learned:
        cross = crossover(table, name)
        noise = "alpha ~ U[0, 6.5], never told" if not name.startswith(("cnn", "lstm")) \
            else "alpha = 1 (the paper's protocol)"
        out.append(f"| {name} | {noise} | "
                   f"{_crossing(cross)} |")
    return [*out, ""]


def _xyz(r) -> str:
    """``x, y, psi`` of an RMSE triple (psi in rad) as ``0.28, 0.23, 11.0`` (psi in mrad)."""
    x, y, psi = (float(v) for v in r)
    return f"{x:.2f}, {y:.2f}, {psi * 1e3:.1f}"


def _crossing(cross: float | None) -> str:
    return "never on 0..6" if cross is None else f"{cross:.2f}"


def protocols_markdown(table: pd.DataFrame, literal: pd.DataFrame) -> list[str]:
    """The paper's numbers, its protocol as lbo trains it (``literal``: rows of observers named
    ``literal-<model>-N<window>``) and ours (the best window of ``table``), side by side: the
    RMSE at alpha 1 and 6 (psi in mrad), the NRMSE growth from 1 to 6 and the crossover with
    our EKF."""
    both = pd.concat([table, literal], ignore_index=True)
    out = ["## The paper's protocol beside ours", "",
           "Trained at alpha = 1 in both. *literal*: the paper's protocol as close as lbo "
           "trains it (experiment=<scale>_literal: the stored noise draw, inputs and targets "
           "scaled by the training set's min and range); *ours*: the best window of our "
           "protocol (fresh noise per window, scaled by the mean and standard deviation). "
           "RMSE x, y (m), psi (mrad).", "",
           "| model | protocol | observer | alpha 1 | alpha 6 | NRMSE growth 1 to 6 "
           "| overtakes the EKF from alpha |", "|---|---|---|---|---|---|---|"]

    def cells(name: str) -> tuple[str, str, str]:
        at = both[both["observer"] == name].set_index("alpha")
        rmse = [_xyz(at.loc[a, ["rmse_x", "rmse_y", "rmse_psi"]]) if a in at.index else "-"
                for a in (1.0, 6.0)]
        growth = (f"{at.loc[6.0, 'nrmse'] / at.loc[1.0, 'nrmse']:.1f}"  # type: ignore[index]  # float labels
                  if {1.0, 6.0} <= set(at.index) else "-")
        return rmse[0], rmse[1], growth

    said: dict[str, list[str]] = {}
    for model in ("cnn", "lstm"):
        p1, p6 = (np.array(PAPER_RMSE[a][model]) for a in (1.0, 6.0))
        growth = nrmse(p6, PAPER_REFERENCE) / nrmse(p1, PAPER_REFERENCE)
        out.append(f"| {model.upper()} | paper | N={PAPER_BEST_WINDOW[model]} | {_xyz(p1)} | "
                   f"{_xyz(p6)} | {growth:.1f} | about {PAPER_CROSSOVER[model]:g} |")
        names = [("literal", o) for o in sorted(set(literal["observer"]))
                 if o.startswith(f"literal-{model}-")]
        best = best_window(table, model)
        names += [("ours", best)] if best else []
        for protocol, name in names:
            a1, a6, growth = cells(name)
            cross = _crossing(crossover(both, name))
            said.setdefault(protocol, []).append(f"{name} {cross}")
            out.append(f"| {model.upper()} | {protocol} | {name} | {a1} | {a6} | {growth} | "
                       f"{cross} |")
    out += ["", "Where each overtakes the EKF: the paper's CNN from alpha of about "
            f"{PAPER_CROSSOVER['cnn']:g} and its LSTM from about {PAPER_CROSSOVER['lstm']:g}; "
            + "; ".join(f"{p}: {', '.join(v)}" for p, v in said.items()) + "."]
    return [*out, "", "![protocols](nrmse_protocols.png)", ""]


class Section(Protocol):
    """A study beyond the paper's tables: its part of report.md, the observers it adds to
    ``nrmse_all.png`` (``headline``), its figure's file name, and the files it writes."""

    @property
    def headline(self) -> tuple[str, ...]: ...

    @property
    def figure(self) -> str: ...

    def markdown(self, table: pd.DataFrame) -> list[str]: ...

    def write(self, folder: Path, table: pd.DataFrame) -> list[Path]: ...


@dataclass(frozen=True)
class Protocols:
    """The paper's protocol as lbo trains it, beside ours: score rows of observers named
    ``literal-<model>-N<window>``: ``literal.csv`` and ``nrmse_protocols.png``."""

    literal: pd.DataFrame
    headline: tuple[str, ...] = ()
    figure: str = "nrmse_protocols.png"

    def markdown(self, table: pd.DataFrame) -> list[str]:
        return protocols_markdown(table, self.literal)

    def write(self, folder: Path, table: pd.DataFrame) -> list[Path]:
        with atomic_path(folder / "literal.csv") as tmp:
            self.literal.to_csv(tmp, index=False)
        both = pd.concat([table, self.literal], ignore_index=True)
        best = (best_window(table, m) for m in ("cnn", "lstm"))
        curves = [*dict.fromkeys(self.literal["observer"]), *(n for n in best if n),
                  *present(table, classical.GRID_PEERS)]
        return [folder / "literal.csv", plots.save(plots.nrmse_curves(
            both, "trained at alpha = 1: the paper's protocol (literal-*) and ours",
            observers=curves), folder / self.figure)]


def present(table: pd.DataFrame, names) -> list[str]:
    """The observers of ``names`` that ``table`` has rows for, in that order."""
    have = set(table["observer"])
    return [n for n in names if n in have]


def md_table(df: pd.DataFrame, digits: int = 3) -> str:
    cols = list(df.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, r in df.iterrows():
        cells = [f"{v:.{digits}g}" if isinstance(v, float) else str(v) for v in r]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def markdown(scale: str, tables: dict[str, pd.DataFrame], table: pd.DataFrame,
             best: dict[str, str | None], runs: dict[str, str], stages: dict[str, dict],
             sections: Sequence[Section] = ()) -> str:
    """report.md: the tables, crossovers, best windows, each section, run ids and stage
    times; the paper's tables (``tables``: Table I and II) only where its observers ran."""
    out = [f"# lbo report: scale `{scale}`", ""]
    if tables:
        out += ["RMSE of the EKF and of the best CNN and LSTM, ours beside the paper's "
                "(psi in mrad).", ""]
        out += _paper_markdown(tables, table, best)
    nr = table.pivot(index="alpha", columns="observer", values="nrmse")
    out += ["## NRMSE at alpha = 1, 3, 6", "",
            md_table(nr.loc[nr.index.isin([1.0, 3.0, 6.0])].reset_index()), ""]
    out += crossover_markdown(table)
    for section in sections:
        out += section.markdown(table)
    out += ["## Runs", "", "| observer | MLflow run id |", "|---|---|"]
    out += [f"| {k} | `{v}` |" for k, v in sorted(runs.items())]
    out += ["", "## Stages", "", "| stage | status | seconds |", "|---|---|---|"]
    out += [f"| {k} | {v.get('status', '')} | {v.get('seconds', float('nan')):.1f} |"
            for k, v in stages.items()]
    paper = ["nrmse_cnn.png", "nrmse_lstm.png"] if tables else []
    figures = ["friction_circle.png", *paper, "nrmse_all.png",
               *(["trajectory_alpha3.png"] if tables else []),
               *(section.figure for section in sections)]
    out += ["", f"Figures: {', '.join(figures)}.", ""]
    return "\n".join(out)


def _paper_markdown(tables: dict[str, pd.DataFrame], table: pd.DataFrame,
                    best: dict[str, str | None]) -> list[str]:
    """The paper's Tables I and II, ours beside its, and its best windows and crossovers."""
    out = []
    for alpha, key in ((1.0, "rmse_alpha1"), (6.0, "rmse_alpha6")):
        t = tables[key].drop(columns=["cnn_observer", "lstm_observer"])
        out += [f"## RMSE at alpha = {alpha:g} (paper Table {'I' if alpha == 1 else 'II'})", "",
                md_table(t), ""]
    out += ["## Best windows and crossovers", "",
            "| architecture | best window (ours) | best window (paper) | overtakes the EKF from "
            "alpha (ours) | (paper) |", "|---|---|---|---|---|"]
    for model in ("cnn", "lstm"):
        name = best.get(model)
        cross = crossover(table, name) if name else None
        ours = _crossing(cross)
        out.append(f"| {model.upper()} | {name or '-'} | N={PAPER_BEST_WINDOW[model]} | {ours} "
                   f"| about {PAPER_CROSSOVER[model]:g} |")
    return out + [""]


def write(folder: str | Path, scale: str, table: pd.DataFrame, runs: dict[str, str],
          stages: dict[str, dict], trajectory: dict[str, Any] | None = None,
          friction_png: str | Path | None = None, sections: Sequence[Section] = ()
          ) -> list[Path]:
    """Write every report file into ``folder``; returns their paths.

    Parameters
    ----------
    table : score table with every observer (learned and classical) at every alpha;
        ``nrmse.csv`` is this table with a ``ratio_to_oracle`` column.
    runs : observer name -> MLflow run id.
    trajectory : arrays for Fig. 6: ``truth``, ``meas`` and one (T, 2) array per estimate.
    friction_png : the data set's friction_circle.png, copied beside the report.
    sections : the studies beyond the paper's tables, each a section of report.md with its
        own files, in this order (:class:`Protocols`, :class:`Robust`, :class:`Dynamic`).
    """
    folder = Path(folder)
    table = with_oracle_ratio(table)
    best = {m: best_window(table, m) for m in ("cnn", "lstm")}
    # the paper's tables and figures where its observers ran (not in a study of the car
    # that slips alone)
    paper = any(best.values())
    tables = {"rmse_alpha1": rmse_table(table, 1.0, best["cnn"], best["lstm"]),
              "rmse_alpha6": rmse_table(table, 6.0, best["cnn"], best["lstm"])} if paper else {}
    written = []
    for key, t in {**tables, "nrmse": table}.items():
        with atomic_path(folder / f"{key}.csv") as tmp:
            t.to_csv(tmp, index=False)
        written.append(folder / f"{key}.csv")
    for model in ("cnn", "lstm") if paper else ():
        names = learned_names(table, model)
        fig = plots.nrmse_curves(table, title=f"{model.upper()} observers against the EKF",
                                 observers=[*names, "ekf"])
        written.append(plots.save(fig, folder / f"nrmse_{model}.png"))
    headline = [n for section in sections for n in section.headline]
    every = ([n for n in (best["cnn"], best["lstm"], *headline) if n]
             + present(table, classical.NAMES))
    written.append(plots.save(plots.nrmse_curves(table, "best observers, classical peers and "
                                                 "the PCRB", observers=every),
                              folder / "nrmse_all.png"))
    for section in sections:
        written += section.write(folder, table)
    if trajectory is not None:
        written.append(plots.save(plots.trajectory(**trajectory), folder / "trajectory_alpha3.png"))
    if friction_png is not None and Path(friction_png).is_file():
        with atomic_path(folder / "friction_circle.png") as tmp:
            tmp.write_bytes(Path(friction_png).read_bytes())
        written.append(folder / "friction_circle.png")
    written.append(write_text(folder / "report.md",
                              markdown(scale, tables, table, best, runs, stages,
                                       sections)))
    return written
