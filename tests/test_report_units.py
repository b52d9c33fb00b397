"""The report's small judgements on hand-made score tables: where an observer overtakes the
EKF (:func:`lbo.scoring.report.crossover`), which window of an architecture is best
(:func:`lbo.scoring.report.best_window`) and each row's NRMSE over the oracle EKF's
(:func:`lbo.scoring.report.with_oracle_ratio`). Every expected number is worked out by hand in a
comment beside it."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from lbo.scoring.metrics import SCORE_COLUMNS
from lbo.scoring.report import best_window, crossover, with_oracle_ratio

GRID = (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
"""The smoke data's alpha grid."""


def table(curves: dict[str, list[float]], alphas=GRID) -> pd.DataFrame:
    """A score table with one row per observer and alpha, NRMSE from ``curves`` (NaN in a
    curve leaves that alpha's row out); the RMSE columns are filler."""
    rows = [{"observer": name, "alpha": a, "rmse_x": 0.1, "rmse_y": 0.1, "rmse_psi": 1e-3,
             "nrmse": v}
            for name, curve in curves.items() for a, v in zip(alphas, curve, strict=True)
            if not math.isnan(v)]
    return pd.DataFrame(rows, columns=SCORE_COLUMNS)


EKF = [0.0, 0.3, 0.6, 0.9, 1.2, 1.5, 1.8]


# crossover -------------------------------------------------------------------------------


def test_crossover_interpolates_between_the_last_alpha_above_and_the_first_below():
    # cnn - ekf: 0.4, 0.2, 0.1, -0.3, -0.5, -0.7, -0.9: above up to alpha 2, below from 3;
    # the line from (2, 0.1) to (3, -0.3) is zero at 2 + 0.1 / 0.4 = 2.25
    t = table({"ekf": EKF, "cnn-N60": [0.4, 0.5, 0.7, 0.6, 0.7, 0.8, 0.9]})
    assert crossover(t, "cnn-N60") == pytest.approx(2.25)


def test_crossover_on_a_quarter_step_grid():
    # lstm - ekf: 0.3, 0.2, 0.03, -0.01, -0.2 at 0, 0.25, 0.5, 0.75, 1:
    # 0.5 + 0.25 * 0.03 / 0.04 = 0.6875
    alphas = (0.0, 0.25, 0.5, 0.75, 1.0)
    t = table({"ekf": [0.0, 0.1, 0.2, 0.3, 0.4],
               "lstm-N80": [0.3, 0.3, 0.23, 0.29, 0.2]}, alphas)
    assert crossover(t, "lstm-N80") == pytest.approx(0.6875)


def test_crossover_is_none_when_the_observer_is_never_below_the_ekf():
    t = table({"ekf": EKF, "cnn-N20": [v + 0.05 for v in EKF]})
    assert crossover(t, "cnn-N20") is None


def test_crossover_is_zero_when_the_observer_is_below_the_ekf_at_every_alpha():
    t = table({"ekf": [0.1, 0.3, 0.6, 0.9, 1.2, 1.5, 1.8],
               "robust": [0.05, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7]})
    assert crossover(t, "robust") == 0.0


def test_crossover_is_zero_when_always_below_even_if_the_grid_starts_above_zero():
    alphas = (1.0, 2.0, 3.0)
    t = table({"ekf": [0.3, 0.6, 0.9], "cnn-N60": [0.2, 0.4, 0.6]}, alphas)
    assert crossover(t, "cnn-N60") == 0.0


def test_crossover_is_none_when_the_observer_is_below_early_but_above_at_the_last_alpha():
    # cnn - ekf: 0.05, -0.1, -0.1, -0.1, 0.1, 0.1, 0.1: below at alpha 1..3 only, so it is
    # not below "from" any alpha on the grid
    t = table({"ekf": EKF, "cnn-N20": [0.05, 0.2, 0.5, 0.8, 1.3, 1.6, 1.9]})
    assert crossover(t, "cnn-N20") is None


def test_crossover_is_the_last_crossing_when_the_curves_cross_twice():
    # cnn - ekf: 0.2, -0.1, 0.1, 0.3, -0.1, -0.2, -0.3: below at 1 only briefly, for good
    # from between 3 and 4: 3 + 0.3 / 0.4 = 3.75 (not the first crossing, 1/3)
    t = table({"ekf": EKF, "cnn-N40": [0.2, 0.2, 0.7, 1.2, 1.1, 1.3, 1.5]})
    assert crossover(t, "cnn-N40") == pytest.approx(3.75)


def test_crossover_at_an_exact_tie_is_the_tied_alpha():
    # equal at alpha 2 (both 0.5), above before, below after
    t = table({"ekf": [0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5],
               "cnn-N60": [0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5]})
    assert crossover(t, "cnn-N60") == 2.0


def test_a_tie_at_the_first_alpha_is_not_below_so_the_crossover_is_that_alpha_not_zero():
    alphas = (0.25, 0.5, 0.75)
    t = table({"ekf": [0.25, 0.5, 0.75], "robust": [0.25, 0.25, 0.25]}, alphas)
    assert crossover(t, "robust") == 0.25


def test_a_tie_at_the_last_alpha_means_no_crossover():
    # below everywhere but equal at alpha 6: never strictly below from an alpha on
    t = table({"ekf": [0.1, 0.4, 0.7, 1.0, 1.3, 1.6, 1.8],
               "cnn-N60": [0.05, 0.3, 0.6, 0.9, 1.2, 1.5, 1.8]})
    assert crossover(t, "cnn-N60") is None


def test_crossover_against_another_baseline():
    # robust - oracle: 0.2, 0.1, -0.1, -0.1, ...: 1 + 0.1 / 0.2 = 1.5; robust - ekf: 0.2,
    # -0.2, -0.7, ...: 0 + 0.2 / 0.4 = 0.5
    t = table({"ekf": [0.1, 0.6, 1.2, 1.8, 2.4, 3.0, 3.6],
               "oracle": [0.1, 0.3, 0.6, 0.9, 1.2, 1.5, 1.8],
               "robust": [0.3, 0.4, 0.5, 0.8, 1.1, 1.4, 1.7]})
    assert crossover(t, "robust", baseline="oracle") == pytest.approx(1.5)
    assert crossover(t, "robust") == pytest.approx(0.5)


def test_crossover_does_not_depend_on_row_order():
    t = table({"ekf": EKF, "cnn-N60": [0.4, 0.5, 0.7, 0.6, 0.7, 0.8, 0.9]})
    shuffled = t.sample(frac=1.0, random_state=3).reset_index(drop=True)
    assert not shuffled["alpha"].is_monotonic_increasing
    assert crossover(shuffled, "cnn-N60") == pytest.approx(2.25)
    # both curves listed from alpha 6 down to 0, in the same order
    backwards = table({"ekf": EKF[::-1], "cnn-N60": [0.9, 0.8, 0.7, 0.6, 0.7, 0.5, 0.4]},
                      GRID[::-1])
    assert crossover(backwards, "cnn-N60") == pytest.approx(2.25)


def test_crossover_compares_only_the_alphas_both_observers_have():
    # the observer is scored at 0, 2, 4, 6 only: cnn - ekf = 0.4, 0.1, -0.3, -0.6, so the
    # line runs from (2, 0.1) to (4, -0.3) over the missing alpha 3: 2 + 2 * 0.1 / 0.4 = 2.5
    nan = float("nan")
    t = table({"ekf": EKF, "cnn-N60": [0.4, nan, 0.7, nan, 0.9, nan, 1.2]})
    assert crossover(t, "cnn-N60") == pytest.approx(2.5)


def test_crossover_is_none_when_the_baseline_or_the_observer_is_missing():
    t = table({"ekf": EKF, "cnn-N60": [0.4, 0.5, 0.7, 0.6, 0.7, 0.8, 0.9]})
    no_baseline, no_observer = crossover(t, "cnn-N60", baseline="oracle"), crossover(t, "lstm")
    assert (no_baseline, no_observer) == (None, None)


# best_window -----------------------------------------------------------------------------


def test_best_window_has_the_lowest_nrmse_averaged_over_alpha_not_at_one_alpha():
    # means: N20 (0.1+0.2+0.9+1.6)/4 = 0.7, N60 (0.3+0.4+0.6+0.7)/4 = 0.5,
    # N100 (0.4+0.5+0.7+0.8)/4 = 0.6; N20 is the best at alpha 0 and 1
    alphas = (0.0, 1.0, 2.0, 3.0)
    t = table({"ekf": [0.0, 0.3, 0.6, 0.9],
               "cnn-N20": [0.1, 0.2, 0.9, 1.6],
               "cnn-N60": [0.3, 0.4, 0.6, 0.7],
               "cnn-N100": [0.4, 0.5, 0.7, 0.8]}, alphas)
    assert best_window(t, "cnn") == "cnn-N60"


def test_best_window_can_be_the_widest_window():
    # means 0.6, 0.5, 0.4: N100 sorts before N20 as text but is chosen on its numbers
    alphas = (1.0, 2.0)
    t = table({"cnn-N20": [0.4, 0.8], "cnn-N60": [0.3, 0.7], "cnn-N100": [0.2, 0.6]}, alphas)
    assert best_window(t, "cnn") == "cnn-N100"


def test_best_window_looks_only_at_its_architecture():
    # the oracle, the robust observer and the LSTM are all lower than any CNN
    alphas = (1.0, 2.0)
    t = table({"oracle": [0.01, 0.02], "robust": [0.02, 0.03], "lstm-N80": [0.05, 0.06],
               "lstm-N20": [0.07, 0.08], "cnn-N20": [0.5, 0.9], "cnn-N60": [0.6, 0.7]},
              alphas)
    assert best_window(t, "cnn") == "cnn-N60"  # 0.65 against 0.7
    assert best_window(t, "lstm") == "lstm-N80"


def test_best_window_is_none_when_the_architecture_is_absent():
    t = table({"ekf": EKF, "oracle": EKF, "robust": EKF, "cnn-N60": EKF})
    assert best_window(t, "lstm") is None


def test_best_window_is_a_plain_string():
    t = table({"lstm-N20": [0.5] * 7, "lstm-N80": [0.4] * 7})
    name = best_window(t, "lstm")
    assert type(name) is str and name == "lstm-N80"


def test_best_window_does_not_prefer_a_window_that_failed_at_the_hard_alphas():
    # N20 is lower at alpha 0..5 but NaN at 6; over every alpha its mean is undefined, so
    # the best window is N60 (mean 0.6), not N20 (mean of six values 0.45)
    nan = float("nan")
    t = table({"cnn-N20": [0.2, 0.3, 0.4, 0.5, 0.6, 0.7, nan],
               "cnn-N60": [0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9]})
    t.loc[len(t)] = {"observer": "cnn-N20", "alpha": 6.0, "rmse_x": np.nan, "rmse_y": np.nan,
                     "rmse_psi": np.nan, "nrmse": np.nan}
    assert best_window(t, "cnn") == "cnn-N60"


# with_oracle_ratio -----------------------------------------------------------------------


def test_ratio_to_oracle_is_each_rows_nrmse_over_the_oracles_at_its_alpha():
    # the oracle rows come last: each row is matched to the oracle by alpha, not position
    alphas = (1.0, 2.0, 3.0)
    t = table({"ekf": [0.3, 1.0, 1.8], "cnn-N60": [0.1, 0.75, 0.6],
               "oracle": [0.2, 0.5, 1.2]}, alphas)
    out = with_oracle_ratio(t)
    got = out.set_index(["observer", "alpha"])["ratio_to_oracle"]
    expected = {("ekf", 1.0): 1.5, ("ekf", 2.0): 2.0, ("ekf", 3.0): 1.5,
                ("cnn-N60", 1.0): 0.5, ("cnn-N60", 2.0): 1.5, ("cnn-N60", 3.0): 0.5,
                ("oracle", 1.0): 1.0, ("oracle", 2.0): 1.0, ("oracle", 3.0): 1.0}
    for key, value in expected.items():
        assert got[key] == pytest.approx(value), key


def test_ratio_to_oracle_is_nan_where_the_oracle_nrmse_is_zero():
    # alpha = 0: the oracle EKF is exact, so no ratio; alpha 1 is 0.4 / 0.2 = 2
    alphas = (0.0, 1.0)
    t = table({"oracle": [0.0, 0.2], "cnn-N20": [0.4, 0.4]}, alphas)
    got = with_oracle_ratio(t).set_index(["observer", "alpha"])["ratio_to_oracle"]
    assert np.isnan(got["cnn-N20", 0.0]) and np.isnan(got["oracle", 0.0])
    assert got["cnn-N20", 1.0] == pytest.approx(2.0)


def test_ratio_to_oracle_is_nan_at_an_alpha_the_oracle_was_not_scored_at():
    nan = float("nan")
    alphas = (1.0, 2.0, 3.0)
    t = table({"oracle": [0.2, nan, 0.6], "ekf": [0.3, 0.6, 0.9]}, alphas)
    got = with_oracle_ratio(t).set_index(["observer", "alpha"])["ratio_to_oracle"]
    assert got["ekf", 1.0] == pytest.approx(1.5)
    assert np.isnan(got["ekf", 2.0])
    assert got["ekf", 3.0] == pytest.approx(1.5)


def test_a_table_without_an_oracle_gets_an_all_nan_ratio_column():
    t = table({"ekf": EKF, "cnn-N60": EKF})
    out = with_oracle_ratio(t)
    assert "ratio_to_oracle" in out.columns
    assert len(out) == len(t)
    assert out["ratio_to_oracle"].isna().all()
    assert out["ratio_to_oracle"].dtype == float


def test_with_oracle_ratio_adds_one_column_and_leaves_the_input_alone():
    alphas = (1.0, 2.0)
    t = table({"oracle": [0.2, 0.4], "ekf": [0.3, 0.5]}, alphas)
    before = t.copy()
    out = with_oracle_ratio(t)
    assert list(out.columns) == [*SCORE_COLUMNS, "ratio_to_oracle"]
    pd.testing.assert_frame_equal(out[SCORE_COLUMNS], before)  # same rows, same order
    pd.testing.assert_frame_equal(t, before)  # the caller's table is not changed
    assert out["ratio_to_oracle"].dtype == float


# the paper's protocol beside ours ----------------------------------------------------------

def test_protocols_section_sets_the_literal_run_beside_ours_and_the_paper():
    from lbo.scoring.report import protocols_markdown

    ours = table({"ekf": EKF, "cnn-N20": [0.5, 0.6, 0.8, 1.0, 1.3, 1.6, 2.0],
                  "cnn-N40": [0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1]})  # N40: below from 4.5
    # literal: below the EKF from 2 on (0.6 = 0.6 at alpha 2 is a tie: not below)
    literal = table({"literal-cnn-N60": [0.5, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]})
    md = "\n".join(protocols_markdown(ours, literal))
    assert "| CNN | paper | N=60 | 0.28, 0.23, 11.0 | 0.91, 0.89, 20.0 | 2.4 | about 2 |" in md
    # growth: 1.0 / 0.5 at alpha 6 over 1; the filler RMSE is 0.10 m, 1.0 mrad
    assert ("| CNN | literal | literal-cnn-N60 | 0.10, 0.10, 1.0 | 0.10, 0.10, 1.0 | 2.0 | 2.00 |"
            in md)
    # ours is the best window (lowest mean NRMSE): cnn-N40, 0.1 above the EKF at 2 and 0.1
    # below at 3, so from 2.5; its growth 1.1 / 0.6
    assert ("| CNN | ours | cnn-N40 | 0.10, 0.10, 1.0 | 0.10, 0.10, 1.0 | 1.8 | 2.50 |"
            in md)
    assert md.count("| LSTM |") == 1  # neither protocol trained an LSTM here: the paper's row
    assert "literal: literal-cnn-N60 2.00; ours: cnn-N40 2.50." in md


# the report's sections ---------------------------------------------------------------------

def test_the_report_writes_each_section_in_the_order_given_with_its_files(tmp_path):
    from lbo.scoring import report, studies

    ours = table({"ekf": EKF, "oracle": [0.0, 0.3, 0.5, 0.7, 0.9, 1.1, 1.3],
                  "adaptive": [0.1, 0.35, 0.6, 0.8, 1.0, 1.2, 1.4],
                  "cnn-N20": [0.5, 0.6, 0.8, 1.0, 1.3, 1.6, 2.0],
                  "lstm-N20": [0.6, 0.7, 0.9, 1.1, 1.4, 1.7, 2.1],
                  "filternet-N40": [0.05, 0.31, 0.52, 0.72, 0.93, 1.12, 1.33]})
    literal = table({"literal-cnn-N60": [0.5, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]})
    sections = [studies.Robust("filternet-N40"), report.Protocols(literal)]
    files = report.write(tmp_path, "smoke", ours, {}, {}, sections=sections)
    text = (tmp_path / "report.md").read_text()
    robust = text.index("## Beyond the paper: one observer for every noise level")
    protocols = text.index("## The paper's protocol beside ours")
    assert robust < protocols < text.index("## Runs")  # in the order given, before the runs
    assert "trajectory_alpha3.png, nrmse_robust.png, nrmse_protocols.png." in text
    for name in ("nrmse_robust.png", "nrmse_protocols.png", "literal.csv"):
        assert tmp_path / name in files and (tmp_path / name).is_file()
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "literal.csv"), literal)
    # the learned peers trained as the robust observer is: their NRMSE and ratio beside it
    peers = ours.assign(observer=ours["observer"].replace({"lstm-N20": "kalmannet-N40"}))
    files = report.write(tmp_path / "peers", "smoke", peers, {}, {},
                         sections=[studies.Robust("filternet-N40", ("kalmannet-N40",))])
    text = (tmp_path / "peers" / "report.md").read_text()
    assert "kalmannet-N40 / oracle" in text and "filternet-N40 / oracle" in text
    assert "the learned peers' worst ratios: `kalmannet-N40` " in text
    bare = tmp_path / "bare"
    report.write(bare, "smoke", ours, {}, {})
    text = (bare / "report.md").read_text()
    assert "## Beyond the paper" not in text and "nrmse_robust.png" not in text
    assert not (bare / "nrmse_robust.png").exists() and not (bare / "literal.csv").exists()
    # a study of the car that slips alone (reproduce study=dynamic): none of the paper's
    # observers ran, so none of its tables or figures
    alone = tmp_path / "alone"
    report.write(alone, "smoke", ours[ours["observer"].isin(["ekf", "oracle", "adaptive"])],
                 {}, {})
    text = (alone / "report.md").read_text()
    assert "Table I" not in text and "Best windows" not in text and "CNN" not in text
    assert "## NRMSE at alpha = 1, 3, 6" in text
    assert "Figures: friction_circle.png, nrmse_all.png." in text
    assert sorted(p.name for p in alone.iterdir()) == ["nrmse.csv", "nrmse_all.png",
                                                       "report.md"]


# the summary a training run ends with ------------------------------------------------------


def test_a_training_run_ends_with_its_nrmse_beside_the_peers_and_its_worst_oracle_ratio():
    from lbo.scoring.grid import summary

    t = table({"cnn-N20": [0.5, 1.2, 1.5, 3.3, 4.0, 5.0, 6.6],
               "ekf": [0.4, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
               "oracle": [0.3, 1.0, 1.5, 2.2, 2.5, 3.0, 3.3]})
    lines = summary(t, "cnn-N20").splitlines()
    assert lines[0].startswith("NRMSE on the test grid")
    assert lines[1].split() == ["observer", "alpha", "1", "alpha", "3", "alpha", "6"]
    assert lines[2].split() == ["cnn-N20", "1.200", "3.300", "6.600"]
    assert lines[3].split() == ["ekf", "1.000", "3.000", "6.000"]
    assert lines[4].split() == ["oracle", "1.000", "2.200", "3.300"]
    # ratios over alpha 0.25-6: 1.2, 1.0, 1.5, 1.6, 1.667, 2.0 (alpha 0 is left out)
    assert lines[5] == "  worst ratio to the oracle over alpha 0.25-6: 2.000 (at alpha 6)"
    # a peer or an alpha the table lacks is left out, and without an oracle there is no ratio
    short = table({"cnn-N20": [0.5, 1.2], "ekf": [0.4, 1.0]}, (0.0, 1.0))
    out = summary(short, "cnn-N20").splitlines()
    assert len(out) == 4 and out[1].split() == ["observer", "alpha", "1"]


def test_a_learned_observers_curve_is_drawn_over_the_filters_it_runs_along():
    from lbo.core import plots

    t = table({"cnn-N20": [0.3, 1.0, 1.5, 2.0, 2.5, 3.0, 3.3],
               "oracle": [0.3, 1.0, 1.5, 2.0, 2.5, 3.0, 3.3],
               "ekf": [0.4, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]})
    fig = plots.nrmse_curves(t)
    z = {line.get_label(): line.get_zorder() for line in fig.axes[0].get_lines()}
    plots.plt.close(fig)
    assert z["cnn-N20"] > z["oracle"] and z["cnn-N20"] > z["ekf"]
