"""Every kind of figure lbo draws, rendered: each axis labelled, each figure with a legend, no
two curves of one panel drawn alike, the truth on top of the estimates, and an observed log's
error panels scaled to what follows its start."""

from __future__ import annotations

import matplotlib.colors as mcolors
import numpy as np
import optuna
import pandas as pd

from lbo.core import plots


def labelled(ax) -> list:
    """The lines of ``ax`` a legend names (matplotlib's own start with an underscore)."""
    return [line for line in ax.get_lines() if not line.get_label().startswith("_")]


def looks(ax) -> list[tuple]:
    return [(mcolors.to_hex(line.get_color()), line.get_linestyle(), line.get_marker(),
             line.get_linewidth()) for line in labelled(ax)]


def check_readable(fig, legend: bool = True) -> None:
    """Every axes that draws something names both its axes; its named curves look apart; the
    figure has a legend (on an axes or on the figure)."""
    drawn = [ax for ax in fig.axes if ax.has_data() and ax.get_label() != "<colorbar>"]
    assert drawn
    for ax in drawn:  # a label may stand on the axes it shares that axis with
        assert any(a.get_xlabel() for a in ax.get_shared_x_axes().get_siblings(ax)), \
            f"an axes without an x label: {ax.get_title()!r}"
        assert any(a.get_ylabel() for a in ax.get_shared_y_axes().get_siblings(ax)), \
            f"an axes without a y label: {ax.get_title()!r}"
        assert len(set(looks(ax))) == len(looks(ax)), f"curves drawn alike: {looks(ax)}"
    if legend:
        assert fig.legends or any(ax.get_legend() is not None for ax in drawn)


def score_table(observers: list[str], alphas=(0.0, 1.0, 3.0, 6.0)) -> pd.DataFrame:
    # the same numbers for every observer: curves that coincide must still be told apart
    return pd.DataFrame([{"observer": o, "alpha": a, "nrmse": 1 + a / 3}
                         for o in observers for a in alphas])


def test_nrmse_curves_draw_four_windows_of_one_network_and_the_oracle_apart():
    names = ["lstm-N20", "lstm-N40", "lstm-N60", "lstm-N80", "filternet-N100", "ekf", "oracle"]
    fig = plots.nrmse_curves(score_table(names), title="all")
    check_readable(fig)
    ax = fig.axes[0]
    style = {line.get_label(): line for line in labelled(ax)}
    # the oracle wide and pale under the learned curve that runs along it
    assert style["oracle"].get_linewidth() > 2 * style["filternet-N100"].get_linewidth()
    assert style["oracle"].get_zorder() < style["filternet-N100"].get_zorder()
    assert ax.get_xlabel() and "NRMSE" in ax.get_ylabel()


def test_nrmse_panels_and_nees_curves_are_readable():
    names = ["cnn-N20", "cnn-N40", "ekf", "oracle", "pcrb"]
    check_readable(plots.nrmse_panels(score_table(names, (0.5, 1.0, 3.0)),
                                      {"learned": names[:2] + ["ekf"], "classical": names[2:]}))
    nees = pd.DataFrame([{"observer": o, "alpha": a, "nees": 3.0, "low": 2.5, "high": 3.5}
                         for o in ("ekf", "ukf", "filternet-N100") for a in (1.0, 3.0)])
    check_readable(plots.nees_curves(nees))


def test_the_test_manoeuvres_name_their_axes_and_what_is_scored():
    t = np.linspace(0, 1, 50)[:, None]
    fig = plots.paths({"hairpin": np.hstack([t, t ** 2]), "double_lane_change":
                       np.hstack([t, np.sin(t)])}, scored_from=10)
    check_readable(fig)
    assert [t.get_text() for t in fig.legends[0].get_texts()] == [
        "run-in (not scored)", "scored", "first scored step"]


def test_the_paths_figure_draws_the_truth_on_top_of_the_estimates():
    t = np.linspace(0, 10, 100)
    truth = np.c_[t, np.sin(t)]
    fig = plots.trajectory(truth, truth + 0.3, "alpha 3", cnn=truth + 0.01, lstm=truth + 0.01)
    check_readable(fig)
    lines = {line.get_label(): line for line in labelled(fig.axes[0])}
    assert lines["ground truth"].get_zorder() > max(lines[n].get_zorder() for n in ("cnn", "lstm"))
    assert lines["ground truth"].get_linestyle() == "--"


def observed(start_error: float):
    """A log of 60 s at 50 Hz whose heading starts ``start_error`` rad off and settles within a
    second, with a covariance, and the EKF beside it."""
    t = np.arange(0, 60, 0.02)
    truth = np.c_[t, np.sin(t / 5), np.zeros_like(t)]
    rng = np.random.default_rng(0)
    est = truth + rng.normal(0, [0.3, 0.4, 0.01], truth.shape)
    est[:50, 2] += start_error
    cov = np.tile(np.diag([0.1, 0.2, 1e-4]), (len(t), 1, 1))
    cov[:50, 2, 2] = 1.0
    ekf = truth + rng.normal(0, [0.5, 0.5, 0.02], truth.shape)
    return plots.observed_log(t, truth + 1.0, est, "robust", truth, cov, {"ekf": ekf})


def test_an_observed_log_has_a_panel_per_variable_scaled_after_its_start():
    fig = observed(start_error=2.0)
    check_readable(fig)
    path, x, y, psi = fig.axes
    assert [a.get_ylabel() for a in (x, y, psi)] == ["x (m)", "y (m)", "psi (mrad)"]
    # each variable its own sigma band: one filled band per error panel
    assert [len(a.collections) for a in (x, y, psi)] == [1, 1, 1]
    # the heading's 2 rad start is left out of its scale: the rest (10-20 mrad) fills it
    assert psi.get_ylim()[1] < 200
    lines = {line.get_label(): line for line in labelled(path)}
    assert lines["truth"].get_zorder() > lines["robust"].get_zorder()


def test_the_optuna_figures_name_their_objective(tmp_path, monkeypatch):
    from lbo.tuning.mirror import _figures

    study = optuna.create_study(direction="minimize")
    for value in (0.5, 0.3):
        trial = study.ask()
        trial.report(value * 2, 0)
        trial.report(value, 1)
        study.tell(trial, value)
    labels = {}
    real_save = plots.save

    def save(fig, path, **kw):
        labels[path.name] = [ax.get_ylabel() for ax in fig.axes]
        return real_save(fig, path, **kw)

    monkeypatch.setattr(plots, "save", save)
    _figures(study, tmp_path)
    assert "val_loss" in labels["optimization_history.png"][0]
    assert "val_loss" in labels["intermediate_values.png"][0]
    assert (tmp_path / "optimization_history.png").stat().st_size > 10_000


def test_outage_errors_and_the_friction_circle_are_readable():
    rng = np.random.default_rng(1)
    check_readable(plots.outage_errors(np.arange(10.0), {
        "ekf": rng.random((3, 10)), "gyro": rng.random((3, 10))}))
    acc = rng.normal(0, 2, (500, 2))
    check_readable(plots.friction_circle(acc, 4.9, np.linspace(-6, 6, 21), rng.random(500) * 20,
                                         rng.uniform(-3, 3, 500), 0.8))
