"""Aggregate statistics of ``hydo eval``: the interquartile mean across runs and its 95 % CI.

Agarwal et al. 2021 ("Deep RL at the edge of the statistical precipice", rliable): report the
interquartile mean (IQM) of per-run scores with a stratified bootstrap confidence interval. rliable
does not import here, so this is the same recipe on scipy.

Scores come as ``strata``: one list per task (for ``hydo eval``: an object split, or one split when
there is no ``--compare``), each a list of runs, each run a 1-D array of per-episode outcomes (1.0 /
0.0 success, or behaviour ids). A run's score is ``run_score(outcomes)`` (default: the mean, i.e. the
success rate).

Point estimate
    ``IQM = scipy.stats.trim_mean(scores, 0.25)`` over every run score of every stratum: the mean of
    what is left after dropping ``floor(n / 4)`` scores from each end. With fewer than 4 scores
    nothing is dropped and the IQM *is* the plain mean (with one run: that run's score).

95 % confidence interval (``scipy.stats.bootstrap``, percentile method, 10 000 resamples, seeded)
    * every stratum has at least 4 runs: resample runs with replacement, independently per stratum
      (rliable's ``StratifiedBootstrap``); the interval covers run-to-run (seed) variation.
    * fewer runs (a seed spread cannot be estimated from 1-3 runs): resample each run's episodes with
      replacement, independently per run and stratum ("stratified by run"), and recompute every
      statistic; the interval then covers episode sampling noise only, and says so. Statistics that
      are biased under resampling (behaviour entropy: a plug-in entropy of resampled episodes is
      lower than the entropy's, so the percentile interval can miss the estimate) pass
      ``episode_bootstrap=False`` and get no interval (``None``) below 4 runs.

A second interval across seeds, for 2-3 runs (``seed_ci_low`` / ``seed_ci_high``)
    The episode interval above says nothing about seed-to-seed variation, and a run bootstrap over 2-3
    runs has too few distinct resamples to stand alone. So these get a two-level ("hierarchical")
    bootstrap as well: in each resample draw a stratum's runs with replacement, then each drawn run's
    episodes with replacement, and take the IQM of the drawn runs' scores (percentile interval,
    ``N_RESAMPLES``, seeded). It covers both noises and is wider than the episode interval wherever
    the runs disagree. Table I prints it after the episode interval (``format_cell``); with one run,
    or four or more (the run bootstrap), it is ``None``.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np
from scipy import stats

CONFIDENCE = 0.95
N_RESAMPLES = 10_000
MIN_RUNS_FOR_RUN_BOOTSTRAP = 4  # below this, bootstrap over episodes (stratified by run)
IQM_TRIM = 0.25

RunScore = Callable[..., np.ndarray]  # (outcomes (..., n), axis=-1) -> (...)


def success_rate(outcomes: np.ndarray, axis: int = -1) -> np.ndarray:
    """A run's score from its per-episode successes (1.0 / 0.0): their mean."""
    return np.mean(outcomes, axis=axis)


def iqm(scores, axis: int | None = None) -> float | np.ndarray:
    """Interquartile mean: ``scipy.stats.trim_mean(scores, 0.25)`` (flattened unless ``axis``)."""
    x = np.asarray(scores, dtype=np.float64)
    if axis is None:
        return float(stats.trim_mean(x.ravel(), IQM_TRIM))
    return stats.trim_mean(x, IQM_TRIM, axis=axis)


def iqm_note(n_scores: int) -> str:
    """What the IQM of ``n_scores`` scores is, in words."""
    cut = int(IQM_TRIM * n_scores)
    if n_scores == 1:
        return "1 score: the IQM is that run's score"
    if cut == 0:
        return f"{n_scores} scores (< 4): the IQM trims nothing and is their mean"
    return (
        f"{n_scores} scores: the IQM is the mean of the middle {n_scores - 2 * cut} (drops {cut} at each end)"
    )


@dataclass(frozen=True)
class Estimate:
    """IQM across runs with its bootstrap confidence interval."""

    iqm: float
    ci_low: float | None  # None: no interval (see ``ci_over``)
    ci_high: float | None
    n_scores: int  # run scores the IQM is taken over (runs x strata)
    min_runs: int  # fewest runs in a stratum
    ci_over: str  # "runs" | "episodes" | "none" (nothing to resample, or no interval)
    note: str  # how to read the numbers
    seed_ci_low: float | None = None  # runs, then episodes (2-3 runs only; module docstring)
    seed_ci_high: float | None = None

    def as_dict(self) -> dict:
        return asdict(self)

    def cell(self, digits: int = 3) -> str:
        """``0.760 [0.718, 0.802]``: the Table I cell (just the IQM when there is no interval), and
        ``; seeds [0.650, 0.850]`` after it where there is a seed interval."""
        return format_cell(self.iqm, self.ci_low, self.ci_high, digits, self.seed_ci_low, self.seed_ci_high)


def format_cell(
    value: float,
    low: float | None,
    high: float | None,
    digits: int = 3,
    seed_low: float | None = None,
    seed_high: float | None = None,
) -> str:
    if low is None or high is None:
        return f"{value:.{digits}f}"
    out = f"{value:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"
    if seed_low is not None and seed_high is not None:
        out += f"; seeds [{seed_low:.{digits}f}, {seed_high:.{digits}f}]"
    return out


def _bootstrap(samples: list[np.ndarray], statistic, seed: int, n_resamples: int) -> tuple[float, float]:
    """Percentile CI of ``statistic(*samples, axis=-1)`` resampling each sample independently.

    Samples of one element are constants (resampling cannot change them); scipy needs two or more.
    """
    varying = [i for i, s in enumerate(samples) if len(s) > 1]
    if not varying:
        value = float(statistic(*[s[None] for s in samples], axis=-1)[0])
        return value, value

    def stat(*resampled, axis=-1):
        batch = resampled[0].shape[:-1]
        full = [np.broadcast_to(s, (*batch, len(s))) for s in samples]
        for i, r in zip(varying, resampled, strict=True):
            full[i] = r
        return statistic(*full, axis=axis)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # constant data: scipy warns, the interval is still exact
        res = stats.bootstrap(
            [samples[i] for i in varying],
            stat,
            n_resamples=n_resamples,
            batch=1000,
            vectorized=True,
            paired=False,
            confidence_level=CONFIDENCE,
            method="percentile",
            rng=np.random.default_rng(seed),
        )
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def _runs_then_episodes(
    strata: list[list[np.ndarray]], run_score: RunScore, seed: int, n_resamples: int
) -> tuple[float, float]:
    """Percentile CI of the IQM under the two-level bootstrap (module docstring): per resample and
    stratum, draw its runs with replacement, then each drawn run's episodes with replacement.

    Numpy in chunks of resamples (a Python loop over chunks, strata and runs only): a 3-seed x 3-split
    Table I at 200 episodes draws ~18M episode indices in all."""
    rng = np.random.default_rng(seed)
    chunk = 1000
    iqms = []
    for start in range(0, n_resamples, chunk):
        b = min(chunk, n_resamples - start)
        drawn_scores = []
        for runs in strata:
            which = rng.integers(0, len(runs), size=(b, len(runs)))  # (b, R): the runs each resample drew
            scores = np.empty((b, len(runs)))
            for k, run in enumerate(runs):
                hit = which == k
                episodes = rng.integers(0, len(run), size=(int(hit.sum()), len(run)))
                scores[hit] = run_score(run[episodes], axis=-1)
            drawn_scores.append(scores)
        iqms.append(iqm(np.concatenate(drawn_scores, axis=-1), axis=-1))
    alpha = 100 * (1 - CONFIDENCE) / 2
    low, high = np.percentile(np.concatenate(iqms), [alpha, 100 - alpha])
    return float(low), float(high)


def interval_estimate(
    strata: Sequence[Sequence[np.ndarray]],
    run_score: RunScore = success_rate,
    seed: int = 0,
    n_resamples: int = N_RESAMPLES,
    episode_bootstrap: bool = True,
) -> Estimate:
    """IQM of the run scores of every stratum and its 95 % stratified bootstrap CI (module docstring).

    ``strata[s][r]`` is run ``r``'s per-episode outcomes (1-D) in stratum ``s`` (e.g. object split).
    """
    strata = [[np.asarray(run, dtype=np.float64).ravel() for run in runs] for runs in strata]
    strata = [runs for runs in strata if runs]
    if not strata or any(len(run) == 0 for runs in strata for run in runs):
        raise ValueError("interval_estimate needs at least one run with at least one episode")
    scores = np.array([float(run_score(run)) for runs in strata for run in runs])
    point = iqm(scores)
    min_runs = min(len(runs) for runs in strata)
    note = iqm_note(len(scores))
    if min_runs >= MIN_RUNS_FOR_RUN_BOOTSTRAP:
        run_samples = [np.array([float(run_score(run)) for run in runs]) for runs in strata]
        low, high = _bootstrap(
            run_samples, lambda *s, axis=-1: iqm(np.concatenate(s, axis=-1), axis=-1), seed, n_resamples
        )
        how = "runs"
        note += f"; 95% CI: percentile bootstrap over runs, stratified by {'split' if len(strata) > 1 else 'task'}"
    elif not episode_bootstrap:
        low = high = None
        how = "none"
        note += f"; no CI with fewer than {MIN_RUNS_FOR_RUN_BOOTSTRAP} runs (biased under episode resampling)"
    else:
        episodes = [run for runs in strata for run in runs]

        def statistic(*s, axis=-1):
            return iqm(np.stack([run_score(x, axis=-1) for x in s], axis=-1), axis=-1)

        low, high = _bootstrap(episodes, statistic, seed, n_resamples)
        how = "episodes" if any(len(e) > 1 for e in episodes) else "none"
        note += (
            f"; 95% CI: percentile bootstrap over episodes, stratified by run (fewer than "
            f"{MIN_RUNS_FOR_RUN_BOOTSTRAP} runs: episode noise only, not seed-to-seed variation)"
        )
        if min_runs >= 2:
            seed_low, seed_high = _runs_then_episodes(strata, run_score, seed, n_resamples)
            note += "; seeds: percentile bootstrap over runs, then over each drawn run's episodes"
            return Estimate(point, low, high, len(scores), min_runs, how, note, seed_low, seed_high)
    return Estimate(point, low, high, len(scores), min_runs, how, note)
