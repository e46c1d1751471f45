"""IQM and its stratified bootstrap CI (hydo_cli/stats.py) against hand-computed values."""

import numpy as np
import pytest

from hydo_cli.stats import Estimate, format_cell, interval_estimate, iqm, iqm_note


def test_iqm_hand_values():
    assert iqm([1, 2, 3, 4, 5, 6, 7, 8]) == pytest.approx(4.5)  # drops 1, 2 and 7, 8: mean(3, 4, 5, 6)
    assert iqm([100, 1, 3, 2, 4]) == pytest.approx(3.0)  # n = 5 drops one at each end: mean(2, 3, 4)
    assert iqm([0.2, 0.4, 0.6, 0.8]) == pytest.approx(0.5)  # mean(0.4, 0.6)
    assert iqm([0.2, 0.9, 0.5]) == pytest.approx(1.6 / 3)  # n < 4 trims nothing: the plain mean
    assert iqm([0.7]) == pytest.approx(0.7)


def test_iqm_note_says_what_it_degenerates_to():
    assert "that run's score" in iqm_note(1)
    assert "trims nothing" in iqm_note(3) and "mean" in iqm_note(3)
    assert "middle 2" in iqm_note(4) and "middle 5" in iqm_note(9)


def test_one_run_bootstraps_its_episodes():
    # 1 run, episodes (1, 0): resampled success rates 0, 0.5, 1 with probabilities 1/4, 1/2, 1/4,
    # so the 2.5th and 97.5th percentiles are 0 and 1.
    e = interval_estimate([[np.array([1.0, 0.0])]])
    assert (e.iqm, e.ci_low, e.ci_high) == (0.5, 0.0, 1.0)
    assert e.ci_over == "episodes" and e.n_scores == 1 and "over episodes, stratified by run" in e.note


def test_episode_bootstrap_is_stratified_by_run():
    # run A (1, 0) varies, run B (1, 1) cannot: the mean of the two is 0.5 + {0, 0.25, 0.5}
    # with probabilities 1/4, 1/2, 1/4 -> CI [0.5, 1.0] around the IQM (= mean of 2 runs) 0.75.
    e = interval_estimate([[np.array([1, 0]), np.array([1, 1])]])
    assert e.iqm == pytest.approx(0.75) and (e.ci_low, e.ci_high) == (0.5, 1.0)
    assert "trims nothing" in e.note


def test_four_runs_bootstrap_over_runs():
    # run scores 0.2, 0.4, 0.6, 0.8; resampling 4 runs gives IQM 0.2 when >= 3 draws are 0.2:
    # P = (4 * 3 + 1) / 4**4 = 5.1% > 2.5%, so the percentile interval is exactly [0.2, 0.8].
    runs = [np.array([1] * k + [0] * (5 - k), dtype=float) for k in (1, 2, 3, 4)]
    e = interval_estimate([runs])
    assert e.ci_over == "runs" and e.min_runs == 4
    assert e.iqm == pytest.approx(0.5)
    assert e.ci_low == pytest.approx(0.2) and e.ci_high == pytest.approx(0.8)
    # scores 0, 0, 1, 1: IQM 0.5; P(IQM = 0) = P(IQM = 1) = 5/16 -> CI [0, 1]
    e = interval_estimate([[np.array([0.0]), np.array([0.0]), np.array([1.0]), np.array([1.0])]])
    assert (e.iqm, e.ci_low, e.ci_high) == (0.5, 0.0, 1.0)


def test_constant_runs_give_a_zero_width_interval_and_strata_are_named():
    e = interval_estimate([[np.full(10, 1.0)] * 5, [np.full(10, 0.0)] * 5])
    assert e.n_scores == 10 and e.iqm == pytest.approx(0.5)  # 5 ones, 5 zeros: middle 6 = 3 + 3
    e1 = interval_estimate([[np.full(4, 0.75)] * 6])
    assert e1.ci_low == pytest.approx(0.75) and e1.ci_high == pytest.approx(0.75)
    assert "stratified by split" in e.note and "stratified by task" in e1.note


def test_single_episode_runs_have_nothing_to_resample():
    e = interval_estimate([[np.array([1.0])]])
    assert (e.iqm, e.ci_low, e.ci_high, e.ci_over) == (1.0, 1.0, 1.0, "none")


def test_seeded_and_reproducible():
    rng = np.random.default_rng(0)
    runs = [[(rng.random(50) < p).astype(float) for p in (0.3, 0.6)]]
    a, b = interval_estimate(runs, seed=3), interval_estimate(runs, seed=3)
    assert a == b and a.ci_low <= a.iqm <= a.ci_high


def test_no_episode_bootstrap_for_biased_statistics():
    e = interval_estimate([[np.array([0.0, 1.0]), np.array([1.0, 1.0])]], episode_bootstrap=False)
    assert e.ci_low is None and e.ci_high is None and e.ci_over == "none"
    assert e.cell() == "0.750"


def test_cells_and_errors():
    assert format_cell(0.76, 0.718, 0.802) == "0.760 [0.718, 0.802]"
    assert Estimate(0.5, 0.25, 0.75, 2, 2, "episodes", "").cell(2) == "0.50 [0.25, 0.75]"
    with pytest.raises(ValueError, match="at least one run"):
        interval_estimate([[]])


def test_two_or_three_runs_also_get_an_interval_across_seeds():
    # three seeds that disagree (success 0.2, 0.5, 0.8 over 200 episodes each): the episode interval
    # of their mean is ~+-0.05, blind to the seeds; runs-then-episodes is ~+-0.25
    runs = [np.array([1.0] * k + [0.0] * (200 - k)) for k in (40, 100, 160)]
    e = interval_estimate([runs], seed=1)
    assert e.iqm == pytest.approx(0.5) and e.ci_over == "episodes"
    assert e.seed_ci_low < e.ci_low <= e.iqm <= e.ci_high < e.seed_ci_high
    assert (e.seed_ci_high - e.seed_ci_low) > 3 * (e.ci_high - e.ci_low)
    # a drawn set of seeds is at best all 0.2 or all 0.8 (1/27 each), plus episode noise
    assert 0.15 < e.seed_ci_low < 0.4 and 0.6 < e.seed_ci_high < 0.85
    assert "seeds: percentile bootstrap over runs" in e.note
    assert (
        e.cell()
        == f"0.500 [{e.ci_low:.3f}, {e.ci_high:.3f}]; seeds [{e.seed_ci_low:.3f}, {e.seed_ci_high:.3f}]"
    )
    # seeds that agree: nothing but episode noise left, so about the episode interval's width
    same = interval_estimate([[runs[1]] * 3], seed=1)
    width, seed_width = same.ci_high - same.ci_low, same.seed_ci_high - same.seed_ci_low
    assert seed_width == pytest.approx(width, rel=0.2)
    # strata (splits) are drawn apart: two seeds per split
    two = interval_estimate([[runs[0], runs[2]], [runs[1], runs[1]]], seed=1)
    assert two.min_runs == 2 and two.seed_ci_low < two.ci_low and two.seed_ci_high > two.ci_high
    assert interval_estimate([[runs[1], runs[1]]], seed=4) == interval_estimate([[runs[1], runs[1]]], seed=4)


def test_one_run_or_four_have_no_seed_interval():
    runs = [np.array([1.0] * k + [0.0] * (20 - k)) for k in (4, 8, 12, 16)]
    for case in ([runs[:1]], [runs]):
        e = interval_estimate(case)
        assert e.seed_ci_low is None and e.seed_ci_high is None and "; seeds" not in e.cell()
    e = interval_estimate([runs[:2]], episode_bootstrap=False)  # biased statistics: no interval at all
    assert e.seed_ci_low is None
