"""Figures: arrays in, matplotlib figures out. Nothing here knows about Hydra or MLflow."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import cast

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from lbo.core.angles import wrap_angle
from lbo.core.atomic import atomic_path


def save(fig, path: str | Path, dpi: int = 110) -> Path:
    """Save a figure atomically (temp file, then rename) and close it."""
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format=Path(path).suffix[1:])
    finally:
        plt.close(fig)
    return Path(path)


def friction_circle(acc: np.ndarray, radius: float, edges: np.ndarray, speed: np.ndarray,
                    heading: np.ndarray, coverage: float):
    """The paper's Fig. 2: density of (a_lat, a_lon) over the friction circle, with speed and
    heading histograms. acc: (S, 2) as (a_lon, a_lat) in m/s^2; speed, heading: (S,)."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2), gridspec_kw={"width_ratios": [1.2, 1, 1]})
    ax = axes[0]
    h = ax.hist2d(acc[:, 1], acc[:, 0], bins=[edges, edges], cmap="viridis", cmin=1)
    fig.colorbar(h[3], ax=ax, label="samples per cell")
    th = np.linspace(0, 2 * np.pi, 200)
    ax.plot(radius * np.cos(th), radius * np.sin(th), "r-", lw=1.2,
            label=f"friction circle ({radius:g} m/s$^2$)")
    ax.set(xlabel="lateral acceleration (m/s$^2$)", ylabel="longitudinal acceleration (m/s$^2$)",
           title=f"friction circle, {coverage:.0%} of cells filled", aspect="equal")
    ax.legend(fontsize=8, loc="upper right")
    axes[1].hist(speed, bins=50, color="tab:blue")
    axes[1].set(xlabel="V (m/s)", ylabel="samples", title="speed")
    axes[2].hist(np.degrees(heading), bins=72, color="tab:green")
    axes[2].set(xlabel="psi (deg)", ylabel="samples", title="heading")
    fig.tight_layout()
    return fig


def paths(xy: dict[str, np.ndarray], scored_from: int = 0):
    """Small multiples of driven paths. xy: name -> (T, 2); the run-in is drawn grey."""
    n = len(xy)
    cols = min(5, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.0 * rows + 0.4), squeeze=False)
    for ax, (name, p) in zip(axes.ravel(), xy.items()):
        ax.plot(p[: scored_from + 1, 0], p[: scored_from + 1, 1], color="0.7", lw=1,
                label="run-in (not scored)")
        ax.plot(p[scored_from:, 0], p[scored_from:, 1], color="tab:blue", lw=1.2,
                label="scored")
        ax.plot(*p[scored_from], "o", color="tab:red", ms=3, label="first scored step")
        ax.set_title(name.replace("_", " "), fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=7)
        ax.set_xlabel("x (m)", fontsize=7)
        ax.set_ylabel("y (m)", fontsize=7)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=8)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return fig


# Classical observers keep one look in every figure; curves that coincide stay visible.
STYLES: dict[str, dict] = {
    "ekf": {"color": "black", "lw": 2.2},
    "ukf": {"color": "tab:orange", "ls": "--", "lw": 1.2},
    # wide and pale: a learned observer's curve that runs along it shows through
    "oracle": {"color": "tab:green", "lw": 5.0, "alpha": 0.45},
    "adaptive": {"color": "tab:olive", "ls": "--", "lw": 1.2},
    "pcrb": {"color": "tab:gray", "ls": ":", "lw": 1.6, "marker": ""},
}


def learned_styles():
    """Endless styles for the curves without one of :data:`STYLES`: a colour, a dash and a
    marker each, so that curves that coincide (four windows of one network) stay apart."""
    colours = ["tab:blue", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:cyan",
               "navy", "darkred", "indigo", "sienna"]
    dashes, markers = ["-", "--", "-.", ":"], ["o", "s", "^", "v", "D", "P", "X", "*", "<"]
    for i in itertools.count():
        yield {"color": colours[i % len(colours)], "ls": dashes[i % len(dashes)],
               "marker": markers[i % len(markers)], "ms": 3.5}


def nrmse_curves(table, title: str = "", observers: list[str] | None = None,
                 styles: dict[str, dict] | None = None, ylabel: str = "NRMSE",
                 reference: float | None = 1.0):
    """NRMSE (or another measure, named by ``ylabel``) against alpha, one curve per observer,
    from a score table (columns ``observer, alpha, nrmse``); a dotted line at ``reference``
    (None: none)."""
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    names = observers or list(dict.fromkeys(table["observer"]))
    # learned observers take colours the classical ones do not use
    palette = learned_styles()
    for name in names:
        rows = table[table["observer"] == name].sort_values("alpha")
        # a learned observer's curve on top: the oracle's often runs along it
        style = {"marker": ".", "lw": 1.4, "zorder": 2 if name in STYLES else 3,
                 **(STYLES.get(name) or next(palette)), **(styles or {}).get(name, {})}
        ax.plot(rows["alpha"], rows["nrmse"], label=name, **style)
    if reference is not None:
        ax.axhline(reference, color="0.6", lw=0.8, ls=":")
    ax.set(xlabel=r"noise scale $\alpha$", ylabel=ylabel, title=title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def trajectory(truth: np.ndarray | None, meas: np.ndarray, title: str = "",
               **estimates: np.ndarray):
    """The paper's Fig. 6: ground truth (None: not drawn), measurements and estimates in the
    (x, y) plane. Every array is (T, 2); NaN rows (no fix, no estimate) are gaps."""
    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    ax.plot(meas[:, 0], meas[:, 1], ".", color="0.7", ms=2.5, label="measurements")
    for (name, est), style in zip(estimates.items(), learned_styles()):
        ax.plot(est[:, 0], est[:, 1], lw=1.3, color=style["color"], ls=style["ls"], label=name)
    if truth is not None:  # on top, thin and dashed: the estimates show around it
        ax.plot(truth[:, 0], truth[:, 1], TRUTH_LINE, color="black", lw=0.9, zorder=5,
                label="ground truth")
    ax.set(xlabel="x (m)", ylabel="y (m)", title=title)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


TRUTH_LINE = "--"
"""The truth's dash in the path figures: drawn on top and thin, so that it and the estimates
under it both show."""

SETTLE_S = 5.0
"""Seconds after an observed log's first estimate that its error panels' scale leaves out:
a filter's start (a heading not yet known) would flatten everything after it."""


def observed_log(t: np.ndarray, meas: np.ndarray, est: np.ndarray, name: str,
                 truth: np.ndarray | None = None, cov: np.ndarray | None = None,
                 others: dict[str, np.ndarray] | None = None):
    """One observed log: the path in the (x, y) plane (fixes, estimate, truth), and below it,
    over time, a panel each for the errors of x, y (m) and psi (mrad) against the truth with
    the estimate's +-2 sigma band of that variable (either alone when the log has no truth or
    the observer no covariance). Each panel is scaled to what follows the first
    :data:`SETTLE_S` seconds.

    t (T,) s; meas, est, truth (T, 3) ``[x, y, psi]`` (NaN rows: no fix, no estimate);
    cov (T, 3, 3) or None; others: more observers' estimates (T, 3) by name, drawn beside
    (their paths, and their errors where there is a truth)."""
    others = others or {}
    styles = learned_styles()
    next(styles)  # the observer's own: blue, solid
    other_style = {k: next(styles) for k in others}
    sigma = None
    if cov is not None and np.isfinite(cov).any():
        sigma = 2 * np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0, None))
    rows = 1 if truth is None and sigma is None else 4
    fig = plt.figure(figsize=(8.0, 4.8 + 1.9 * (rows - 1)))
    grid = fig.add_gridspec(rows, 1, height_ratios=[2.2] + [1] * (rows - 1))
    ax = fig.add_subplot(grid[0])
    ax.plot(meas[:, 0], meas[:, 1], ".", color="0.65", ms=2.5, label="fixes")
    ax.plot(est[:, 0], est[:, 1], lw=1.3, color="tab:blue", label=name)
    for k, other in others.items():
        ax.plot(other[:, 0], other[:, 1], lw=1.0, color=other_style[k]["color"],
                ls=other_style[k]["ls"], label=k)
    if truth is not None:  # on top, thin and dashed: the estimates show around it
        ax.plot(truth[:, 0], truth[:, 1], TRUTH_LINE, color="black", lw=0.9, zorder=5,
                label="truth")
    ax.set(xlabel="x, east (m)", ylabel="y, north (m)", title=f"{name} on {len(t)} rows")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if rows == 1:
        fig.tight_layout()
        return fig
    err = None
    if truth is not None:
        err = est - truth
        err[:, 2] = wrap_angle(err[:, 2])
    started = np.isfinite(est).all(1)
    settled = (t >= t[int(np.argmax(started))] + SETTLE_S) if started.any() else started
    panels = [fig.add_subplot(grid[1])]
    panels += [fig.add_subplot(grid[i], sharex=panels[0]) for i in (2, 3)]
    for c, (ax, label, scale, unit) in enumerate(zip(
            panels, ("x", "y", "psi"), (1.0, 1.0, 1e3), ("m", "m", "mrad"))):
        lines = []
        if sigma is not None:
            ax.fill_between(t, -scale * sigma[:, c], scale * sigma[:, c], color="tab:blue",
                            alpha=0.18, lw=0, label=f"{name}: +-2 sigma")
            lines.append(sigma[:, c])
        if err is not None:
            ax.plot(t, scale * err[:, c], lw=0.9, color="tab:blue", label=f"{name}: error")
            lines.append(err[:, c])
            for k, other in others.items():
                e = other[:, c] - cast(np.ndarray, truth)[:, c]  # an err: a truth
                e = wrap_angle(e) if c == 2 else e
                ax.plot(t, scale * e, lw=0.8, color=other_style[k]["color"],
                        ls=other_style[k]["ls"], label=f"{k}: error")
                lines.append(e)
        ax.axhline(0.0, color="0.4", lw=0.6)
        # after the start: its wide first steps would flatten the rest
        spread = np.abs(np.stack(lines)[:, settled if settled.any() else slice(None)])
        top = np.nanpercentile(spread, 99) if np.isfinite(spread).any() else np.nan
        if np.isfinite(top) and top > 0:
            ax.set_ylim(-1.5 * scale * top, 1.5 * scale * top)
        ax.set_ylabel(f"{label} ({unit})")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2, loc="upper right")
    panels[-1].set_xlabel("t (s)")
    panels[0].set_title(("error against the truth" if sigma is None else
                         "the estimate's uncertainty" if err is None else
                         "error against the truth, and the observer's own +-2 sigma")
                        + f" (scaled to the rows after the first {SETTLE_S:g} s)", fontsize=10)
    fig.tight_layout()
    return fig


def nees_curves(table, title: str = "calibration: mean NEES against alpha"):
    """Mean NEES per alpha of each observer (log scale), the 95% band of a consistent filter
    shaded; a table of :func:`lbo.scoring.metrics.nees_table` rows."""
    fig, ax = plt.subplots(figsize=(7, 4.2))
    band = table.drop_duplicates("alpha").sort_values("alpha")
    ax.fill_between(band["alpha"], band["low"], band["high"], color="0.85",
                    label="95% band (consistent)")
    ax.axhline(3.0, color="0.5", lw=0.8)
    styles = ["-", "--", ":", "-."]  # curves that coincide (the EKF and the UKF) stay visible
    for i, (name, rows) in enumerate(table.groupby("observer", sort=False)):
        rows = rows.sort_values("alpha")
        ax.plot(rows["alpha"], rows["nees"], ls=styles[i % 4], marker="os^dv"[i % 5], ms=3,
                lw=1.2, label=name)
    ax.set_yscale("log")
    ax.set_xlabel("alpha (measurement noise scale)")
    ax.set_ylabel("mean NEES (3 degrees of freedom)")
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def nrmse_panels(table, panels: dict[str, list[str]], title: str = "",
                 points: dict[str, list[str]] | None = None, styles: dict[str, dict] | None = None):
    """NRMSE against alpha > 0 on a log axis, one panel per entry of ``panels`` (panel title ->
    observers drawn as curves), from a score table (columns ``observer, alpha, nrmse``).
    ``points``: panel title -> observers drawn as markers only (e.g. published numbers)."""
    longest = max(len(o) for o in panels.values())
    fig, axes = plt.subplots(1, len(panels), figsize=(7.0 * len(panels), 4.6 + 0.14 * longest),
                             squeeze=False, sharey=True)
    for ax, (name, observers) in zip(axes[0], panels.items()):
        palette = learned_styles()
        for obs in observers:
            rows = table[(table["observer"] == obs) & (table["alpha"] > 0)].sort_values("alpha")
            style = {"lw": 1.3, "zorder": 2 if obs in STYLES else 3,
                     **(STYLES.get(obs) or (styles or {}).get(obs) or next(palette))}
            ax.plot(rows["alpha"], rows["nrmse"], label=obs, **style)
        for marker, obs in zip("sDv^", (points or {}).get(name, [])):
            rows = table[table["observer"] == obs].sort_values("alpha")
            ax.plot(rows["alpha"], rows["nrmse"], marker, ms=8, color="black", mfc="none",
                    label=obs)
        ax.set(xlabel=r"noise scale $\alpha$", title=name, yscale="log")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=6.5, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.13))
    axes[0][0].set_ylabel("NRMSE (our EKF at alpha = 1 is 1)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def outage_errors(seconds: np.ndarray, errors: dict[str, np.ndarray], title: str = ""):
    """The position error (m) through a GNSS outage, one line per observer: its median over
    the outages, with the band between the smallest and the largest. seconds (L,) into the
    outage; errors: observer -> (K, L) the error through each of K outages. Errors that span
    decades are drawn on a log scale, and each line has its own dash, so that observers with
    the same errors do not hide one another."""
    fig, ax = plt.subplots(figsize=(7.5, 4.4))
    styles = zip(itertools.cycle([f"C{i}" for i in range(10)]),
                 itertools.cycle(["-", "--", ":", "-."]))
    for (name, err), (color, dash) in zip(errors.items(), styles):
        ax.plot(seconds, np.nanmedian(err, 0), lw=1.6, color=color, ls=dash,
                label=f"{name} (median of {len(err)})")
        ax.fill_between(seconds, np.nanmin(err, 0), np.nanmax(err, 0), color=color,
                        alpha=0.08, lw=0)
    every = np.concatenate([e[np.isfinite(e) & (e > 0)] for e in errors.values()])
    if len(every) and every.max() > 30 * np.percentile(every, 5):
        ax.set_yscale("log")
    ax.set(xlabel="seconds into the outage", ylabel="position error (m)",
           title=title or "through a GNSS outage: median, and the band of every outage")
    ax.grid(alpha=0.3, which="both")
    # below the axes: the lines it names run through every corner of them
    ax.legend(fontsize=7.5, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    fig.tight_layout()
    return fig
