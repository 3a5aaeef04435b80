"""The intervals and aggregates the benchmark tables report: a two-level (seeds, then episodes) percentile bootstrap
of the mean success, rliable's interquartile mean, and the Wilson interval of one seed's rate. Written in numpy, since
rliable 1.2 does not import beside this stack, and its bootstrap resamples runs only, which with 1-3 seeds ignores the
episodes' own sampling noise."""

from __future__ import annotations

import math

import numpy as np


def bootstrap_ci(per_seed: list[list[int]], n: int, rng: np.random.Generator) -> tuple[float, float]:
    """95 % interval of the mean success: resample seeds, then episodes within each resampled seed."""
    runs = [np.asarray(s, dtype=float) for s in per_seed if len(s)]
    if not runs:
        return float("nan"), float("nan")
    means = np.empty(n)
    for i in range(n):
        pick = rng.integers(0, len(runs), len(runs))
        means[i] = np.mean([runs[j][rng.integers(0, len(runs[j]), len(runs[j]))].mean() for j in pick])
    lo, hi = np.percentile(means, [2.5, 97.5])
    return float(lo), float(hi)


def iqm(values: list[float]) -> float:
    """Interquartile mean (rliable's aggregate): the mean of the middle 50 % of the sorted values."""
    v = np.sort(np.asarray(values, dtype=float))
    if len(v) == 0:
        return float("nan")
    k = int(np.floor(0.25 * len(v)))
    return float(v[k : len(v) - k].mean())


def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """95 % Wilson score interval of a success rate k/n."""
    if n == 0:
        return float("nan"), float("nan")
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def iqm_ci(rates: list[float], episodes: list[int], n: int, rng: np.random.Generator) -> tuple[float, float, float]:
    """IQM over runs of a success rate, with rliable's stratified bootstrap made two-level: resample the runs, then
    each resampled run's episodes (a binomial draw of its rate over its episode count), so that a curve point of 1-3
    seeds on 30 episodes still carries the episodes' noise. Returns (IQM, 2.5 %, 97.5 %)."""
    p = np.asarray(rates, dtype=float)
    k = np.asarray(episodes, dtype=int)
    if len(p) == 0:
        return float("nan"), float("nan"), float("nan")
    if len(p) != len(k) or np.any(k <= 0) or np.any((p < 0) | (p > 1)):
        raise ValueError(
            f"iqm_ci: rates {rates} and episode counts {episodes} must pair rates in [0, 1] with counts > 0"
        )
    pick = rng.integers(0, len(p), (n, len(p)))
    draws = rng.binomial(k[pick], p[pick]) / k[pick]
    draws.sort(axis=1)
    cut = int(np.floor(0.25 * len(p)))
    boot = draws[:, cut : len(p) - cut].mean(axis=1)
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return iqm(list(p)), float(lo), float(hi)
