"""The statistics every study reports: rates with intervals that respect how the episodes were drawn, and an
exact paired test for every difference a report states.

An evaluation grid is ``outcomes`` (R, S): R training seeds of one model, S test scenes (episode seeds), the
same S scenes for every model of a table (paired), 1 = success. Episodes of one training seed share its
weights and episodes of one scene share its layout, so neither seeds nor scenes are independent draws:

- :func:`cluster_bootstrap` resamples training seeds and scenes independently (a two-way cluster bootstrap)
  and reports the percentile interval of the mean. With few training seeds (3) the seed resampling is coarse;
  the interval is still wider, and more honest, than one that pools the R x S episodes as independent.
- :func:`paired_difference` gives the same interval for the difference of two models on the same grid
  (the same resampled seeds and scenes for both), and :func:`paired_exact_test`'s p-value.
- :func:`paired_exact_test`: a sign-flip (permutation) test on the per-scene differences of the two models'
  mean success over their seeds. Under the null hypothesis (the two models are exchangeable on every
  scene) each scene's difference is as likely negated; the p-value is the exact probability, over all
  2^S sign patterns, of a total at least as far from zero as the observed one, computed by convolution
  (the differences are multiples of 1 / R). With one training seed it is the exact McNemar test. It answers
  "do these trained networks succeed equally often on scenes like these?": the training seeds are fixed.
- :func:`seed_permutation_test`: the exact two-sample permutation test on the training seeds' success rates
  (each seed's mean over the same scenes). It answers "does the method succeed equally often, over training
  runs?": the seeds are the sample. With R training seeds per method its smallest p-value is 2 / C(2R, R)
  (0.1 for 3 seeds, 0.0079 for 5).
- :func:`holm`: Holm's step-down adjustment of a table's p-values (the family: every comparison the table
  states), so that the chance of any false claim in the table stays under alpha.

Every function is deterministic (a fixed generator), so a report rebuilt from its record is identical.
"""

from __future__ import annotations

import itertools
import math
from fractions import Fraction

import numpy as np

BOOTSTRAP_SAMPLES = 10_000
BOOTSTRAP_SEED = 0
ALPHA = 0.05


def _grid(outcomes) -> np.ndarray:
    grid = np.asarray(outcomes, dtype=np.float64)
    if grid.ndim != 2 or grid.size == 0:
        raise ValueError(f"outcomes must be (training seeds, scenes) with at least one of each, got shape {grid.shape}")
    if not np.isin(grid, (0.0, 1.0)).all():
        raise ValueError("outcomes must be 0 (failure) or 1 (success)")
    return grid


def _resampled_means(grids: list[np.ndarray], samples: int, seed: int) -> np.ndarray:
    """(samples, len(grids)): the mean of each grid over the same resampled scenes, and the same resampled seeds
    where a grid has as many as the first (each its own draw of its seeds otherwise)."""
    r, s = grids[0].shape
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, r, (samples, r))
    cols = rng.integers(0, s, (samples, s))
    out = np.empty((samples, len(grids)))
    scenes = _counts(cols, s)  # (samples, s): how often each scene is drawn
    for i, g in enumerate(grids):
        own = rows if g.shape[0] == r else rng.integers(0, g.shape[0], (samples, g.shape[0]))
        # the mean over the resampled (seed, scene) cells, as counts: sum_ij n_i g_ij m_j / (R s), exact in float64
        # (whole numbers), so the same as averaging the drawn cells
        out[:, i] = np.einsum("kj,kj->k", _counts(own, g.shape[0]) @ g, scenes) / (own.shape[1] * s)
    return out


def _counts(draws: np.ndarray, n: int) -> np.ndarray:
    """(samples, n): how many times each of 0..n-1 appears in each row of ``draws`` (samples, m)."""
    k = draws.shape[0]
    return np.bincount((draws + n * np.arange(k)[:, None]).ravel(), minlength=k * n).reshape(k, n).astype(np.float64)


def cluster_bootstrap(
    outcomes, samples: int = BOOTSTRAP_SAMPLES, seed: int = BOOTSTRAP_SEED, alpha: float = ALPHA
) -> tuple[float, float, float]:
    """(mean, low, high): the success rate of an (R, S) grid and its (1 - alpha) two-way cluster-bootstrap interval."""
    grid = _grid(outcomes)
    means = _resampled_means([grid], samples, seed)[:, 0]
    lo, hi = np.quantile(means, [alpha / 2, 1 - alpha / 2])
    return float(grid.mean()), float(lo), float(hi)


def paired_difference(
    a, b, samples: int = BOOTSTRAP_SAMPLES, seed: int = BOOTSTRAP_SEED, alpha: float = ALPHA
) -> tuple[float, float, float]:
    """(difference, low, high): mean(a) - mean(b) of two (R_a, S) and (R_b, S) grids on the same scenes, with its
    two-way cluster-bootstrap interval: the same resampled scenes for both; the same resampled seeds where R_a = R_b,
    each model's own draw of its seeds otherwise."""
    ga, gb = _grid(a), _grid(b)
    if ga.shape[1] != gb.shape[1]:
        raise ValueError(f"paired grids must share their scenes: {ga.shape[1]} and {gb.shape[1]} scenes")
    means = _resampled_means([ga, gb], samples, seed)
    diff = means[:, 0] - means[:, 1]
    lo, hi = np.quantile(diff, [alpha / 2, 1 - alpha / 2])
    return float(ga.mean() - gb.mean()), float(lo), float(hi)


def paired_exact_test(a, b) -> float:
    """Two-sided exact p-value that models a and b ((R_a, S) and (R_b, S) grids on the same S scenes) succeed
    equally often: the sign-flip test on the per-scene differences of their mean success (module docstring)."""
    ga, gb = _grid(a), _grid(b)
    if ga.shape[1] != gb.shape[1]:
        raise ValueError(f"paired grids must share their scenes: {ga.shape[1]} and {gb.shape[1]} scenes")
    ra, rb = ga.shape[0], gb.shape[0]
    unit = math.lcm(ra, rb)  # per-scene differences are whole multiples of 1 / unit
    diffs = np.rint(ga.sum(0) * (unit // ra) - gb.sum(0) * (unit // rb)).astype(np.int64)
    observed = abs(int(diffs.sum()))
    steps = [abs(int(d)) for d in diffs if d]
    if not steps:
        return 1.0
    # distribution of the sum of +-d over the non-zero scenes, as exact counts (Python integers: no overflow)
    total = sum(steps)
    counts = [0] * (2 * total + 1)
    counts[total] = 1
    for d in steps:
        nxt = [0] * (2 * total + 1)
        for value, c in enumerate(counts):
            if c:
                nxt[value - d] += c
                nxt[value + d] += c
        counts = nxt
    extreme = sum(c for value, c in enumerate(counts) if abs(value - total) >= observed)
    return float(Fraction(extreme, 2 ** len(steps)))


def seed_permutation_test(a, b) -> float:
    """Two-sided exact p-value that two methods' training seeds ((R_a, S) and (R_b, S) grids on the same S scenes)
    succeed equally often: every split of the R_a + R_b seed rates into groups of R_a and R_b, counted when its
    difference of means is at least as far from zero as the observed one (module docstring)."""
    ga, gb = _grid(a), _grid(b)
    if ga.shape[1] != gb.shape[1]:
        raise ValueError(f"paired grids must share their scenes: {ga.shape[1]} and {gb.shape[1]} scenes")
    ra = ga.shape[0]
    rates = [int(x) for x in np.concatenate([ga.sum(1), gb.sum(1)])]  # successes per seed, over the same scenes
    total, rb = sum(rates), len(rates) - ra

    def gap(group: tuple[int, ...]) -> Fraction:  # |mean(a) - mean(b)| in successes per seed, exactly
        first = sum(rates[i] for i in group)
        return abs(Fraction(first, ra) - Fraction(total - first, rb))

    observed = gap(tuple(range(ra)))
    splits = list(itertools.combinations(range(len(rates)), ra))
    return float(Fraction(sum(gap(g) >= observed for g in splits), len(splits)))


def holm(pvalues) -> list[float]:
    """Holm's step-down adjusted p-values of one family of comparisons, in the given order: the i-th smallest p
    times (m - i + 1), kept non-decreasing, at most 1."""
    ps = [float(p) for p in pvalues]
    m, adjusted, running = len(ps), [0.0] * len(ps), 0.0
    for rank, i in enumerate(sorted(range(m), key=lambda i: ps[i])):
        running = max(running, min(1.0, (m - rank) * ps[i]))
        adjusted[i] = running
    return adjusted


def describe_p(p: float, alpha: float = ALPHA, holm_p: float | None = None) -> str:
    """``p = 0.012``, ``p = 0.41, not significant``; with Holm's adjusted p of its table: ``p = 0.012, Holm 0.048``
    or ``p = 0.042, Holm 0.13, not significant`` (significance judged on Holm's)."""
    judged = p if holm_p is None else holm_p
    shown = f"p = {_p(p)}" + ("" if holm_p is None else f", Holm {_p(holm_p)}")
    return shown + ("" if judged < alpha else ", not significant")


def _p(p: float) -> str:
    return f"{p:.2g}" if p >= 0.001 else f"{p:.1e}"


FAMILY_NOTE = (
    "Paired test: the exact sign-flip test over scenes (these trained networks, on these scenes); seed test: the exact "
    "permutation test over training seeds (the method, over training runs). Each is Holm-corrected within its table "
    "(the family: every comparison the table states), and judged on Holm's p."
)


def partial_family_note(recorded: int, family: int) -> list[str]:
    """A report's lines under a table whose rows are partly pending: Holm's correction is over the ``recorded`` of its
    ``family`` comparisons, so not final; none once every row is in (or none is)."""
    if not 0 < recorded < family:
        return []
    return [
        "",
        f"Pending rows: {recorded} of the table's {family} comparisons are recorded, and Holm's correction here is "
        f"over those {recorded}; it is taken again over all {family} when the rest are in, so these Holm p-values are "
        "not final.",
    ]


def compare(grid, base) -> dict:
    """One row's comparison with ``base`` ((R, S) grids on the same scenes): the difference and its interval (``delta``,
    ``ci``), the paired test over scenes (``p``) and the test over training seeds (``p_seeds``)."""
    d, lo, hi = paired_difference(grid, base)
    return {
        "delta": d,
        "ci": [lo, hi],
        "p": paired_exact_test(grid, base),
        "p_seeds": seed_permutation_test(grid, base),
    }


def holm_family(comparisons, keys=("p", "p_seeds")) -> None:
    """Holm-correct one table's comparisons (the family: every one it states) in place: ``KEY_holm`` beside each of
    their ``keys``."""
    comparisons = list(comparisons)
    for key in keys:
        for c, adjusted in zip(comparisons, holm([c[key] for c in comparisons])):
            c[f"{key}_holm"] = adjusted


def agrees(p_holm: float, ci) -> bool:
    """Whether a Holm-judged test and a difference's interval say the same: significant exactly when the interval
    leaves out 0."""
    return (p_holm < ALPHA) == (ci[0] > 0 or ci[1] < 0)


def disagreements(comparisons: dict[str, dict], labels: dict[str, str]) -> list[str]:
    """One sentence per comparison (``ci``, ``p_holm``) whose Holm-judged paired test and interval disagree, saying
    which holds."""
    out = []
    for name, c in comparisons.items():
        if agrees(c["p_holm"], c["ci"]):
            continue
        lo, hi = (f"{100 * x:+.0f}" for x in c["ci"])
        if c["p_holm"] < ALPHA:
            out.append(
                f"{labels.get(name, name)}: the paired test is significant (Holm p = {_p(c['p_holm'])}) but the interval "
                f"({lo} to {hi}) includes 0: the difference holds on these scenes for these networks, not beyond them."
            )
        else:
            out.append(
                f"{labels.get(name, name)}: the interval ({lo} to {hi}) leaves out 0 but the paired test is not significant "
                f"after Holm (p = {_p(c['p_holm'])}): the difference is not established; the test holds."
            )
    return out
