"""The report statistics beside the paired scene test: Holm's adjustment of a table and the test over training
seeds, each checked against a reference (hand-computed values, scipy's permutation test)."""

import numpy as np
import pytest
from scipy import stats as scipy_stats

from studies.stats import describe_p, holm, seed_permutation_test


def test_holm_adjusts_a_family_step_down_in_the_given_order():
    # sorted: 0.01 x 4 = 0.04, 0.03 x 3 = 0.09, 0.04 x 2 = 0.08 -> kept at 0.09 (monotone), 0.5 x 1
    assert holm([0.01, 0.04, 0.03, 0.5]) == pytest.approx([0.04, 0.09, 0.09, 0.5])
    assert holm([0.9, 0.8]) == [1.0, 1.0] and holm([0.6, 0.7, 0.01]) == pytest.approx([1.0, 1.0, 0.03])
    assert holm([]) == [] and holm([0.042]) == [0.042]


def test_a_holm_p_over_alpha_is_not_significant_whatever_the_raw_p():
    assert describe_p(0.042, holm_p=0.13) == "p = 0.042, Holm 0.13, not significant"
    assert describe_p(0.004, holm_p=0.016) == "p = 0.004, Holm 0.016"
    assert describe_p(0.042) == "p = 0.042"


@pytest.mark.parametrize("seeds", [(3, 3), (5, 5), (3, 5), (4, 2)])
def test_the_seed_test_is_scipys_exact_permutation_test(seeds):
    rng = np.random.default_rng(sum(seeds))
    a = (rng.random((seeds[0], 20)) < 0.7).astype(float)
    b = (rng.random((seeds[1], 20)) < 0.4).astype(float)
    ref = scipy_stats.permutation_test(
        (a.mean(1), b.mean(1)),
        lambda x, y: abs(x.mean() - y.mean()),
        permutation_type="independent",
        alternative="greater",
        n_resamples=10**6,  # more than the splits: scipy enumerates them all
    )
    assert seed_permutation_test(a, b) == pytest.approx(ref.pvalue, rel=1e-12)


def test_the_seed_test_cannot_go_below_its_smallest_p_with_few_seeds():
    ones, zeros = np.ones((3, 20)), np.zeros((3, 20))
    assert seed_permutation_test(ones, zeros) == pytest.approx(0.1)  # 2 / C(6, 3): 3 seeds cannot show a difference
    assert seed_permutation_test(np.ones((5, 20)), np.zeros((5, 20))) == pytest.approx(2 / 252)
    assert seed_permutation_test(ones, ones) == 1.0
    with pytest.raises(ValueError, match="share their scenes"):
        seed_permutation_test(ones, np.ones((3, 19)))
