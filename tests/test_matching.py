"""Sinkhorn with a dustbin: marginals, the two iterations agree, mutual matches."""

from __future__ import annotations

import numpy as np
import pytest

from logdesc_rt.matching import (
    _augmented_scores,
    _log_marginals,
    log_domain_sinkhorn,
    log_optimal_transport,
    matches_as_array,
    mutual_matches,
)


def reference_log_assignment(scores, dustbin_score, iterations):
    augmented = _augmented_scores(scores, dustbin_score)
    log_row, log_column, log_total = _log_marginals(*scores.shape)
    log_u, log_v = log_domain_sinkhorn(augmented, log_row, log_column, iterations)
    return augmented + log_u[:, None] + log_v[None, :] + log_total


@pytest.mark.parametrize("shape", [(50, 40), (40, 50), (1, 7), (64, 64)])
def test_sinkhorn_meets_its_marginals(shape):
    rng = np.random.default_rng(0)
    scores = rng.normal(scale=2.0, size=shape)
    plan = np.exp(log_optimal_transport(scores, dustbin_score=1.0, iterations=500))
    rows, columns = shape
    # Real rows and columns carry mass 1, the dustbins carry the other side's size.
    assert np.allclose(plan[:rows].sum(axis=1), 1.0, atol=1e-6)
    assert np.allclose(plan[:, :columns].sum(axis=0), 1.0, atol=1e-6)
    assert np.isclose(plan[rows].sum(), columns, atol=1e-6)
    assert np.isclose(plan[:, columns].sum(), rows, atol=1e-6)


@pytest.mark.parametrize("scale", [100.0, 500.0, 5000.0])
def test_huge_score_ranges_stay_exact(scale):
    """exp() of these ranges over- and underflows float64; the log-domain reference does not, and
    the float32 reader gives its matches (through its fallback where a scaling leaves float32)."""
    from logdesc_rt.matching import sinkhorn_matches

    rng = np.random.default_rng(2)
    scores = rng.normal(scale=scale, size=(60, 50))
    result = log_optimal_transport(scores, dustbin_score=0.0, iterations=20)
    assert np.isfinite(result).all()
    # The last update is the columns': after it every real column carries mass 1.
    assert np.allclose(np.exp(result)[:, :-1].sum(axis=0), 1.0, atol=1e-6)
    matched = mutual_matches(result)
    reference = set(zip(matched.source_index, matched.target_index))
    fast = sinkhorn_matches(scores, 0.0, 20)
    assert np.isfinite(fast.confidence).all() and len(fast) > 0
    # Such ranges make many entries exact ties (probability 0.5 to float32's precision), so
    # the two may break a few differently; all others agree.
    agreed = len(reference & set(zip(fast.source_index, fast.target_index)))
    assert agreed >= 0.9 * max(len(reference), len(fast))


def test_mutual_matches_recover_a_permutation_and_the_dustbin():
    """The paper's reading (dustbin in the mutual test) leaves points without a counterpart
    unmatched; the default reading (the dustbin left out of it) keeps the permutation too."""
    rng = np.random.default_rng(3)
    permutation = rng.permutation(40)
    scores = np.full((40, 40), -5.0)
    scores[np.arange(40), permutation] = 5.0
    scores[:5] = -5.0  # the first five source points have no counterpart
    log_assignment = log_optimal_transport(scores, dustbin_score=0.0, iterations=100)
    matches = mutual_matches(log_assignment, dustbin_in_mutual_test=True)
    assignment = matches_as_array(matches, 40)
    assert np.all(assignment[:5] == -1)
    assert np.array_equal(assignment[5:], permutation[5:])
    assert np.all((matches.confidence > 0.5) & (matches.confidence <= 1.0))
    default = matches_as_array(mutual_matches(log_assignment), 40)
    assert np.array_equal(default[5:], permutation[5:])


def test_same_input_same_output():
    scores = np.random.default_rng(4).normal(size=(30, 20))
    assert np.array_equal(log_optimal_transport(scores, 1.0), log_optimal_transport(scores.copy(), 1.0))


@pytest.mark.parametrize(
    ("scores", "dustbin", "message"),
    [
        (np.zeros((3,)), 1.0, r"not \(N, M\)"),
        (np.zeros((0, 4)), 1.0, r"not \(N, M\)"),
        (np.array([[np.nan, 0.0]]), 1.0, "NaN or inf"),
        (np.zeros((2, 2)), np.inf, "not finite"),
    ],
)
def test_bad_scores_raise(scores, dustbin, message):
    with pytest.raises(ValueError, match=message):
        log_optimal_transport(scores, dustbin)


# -- the runtime's float32 reader ------------------------------------------------------------


def _structured_scores(rng, rows, columns, strength, matched):
    """Scores with ``matched`` strong true pairs over a noise floor, like a trained network's."""
    from logdesc_rt.matching import sinkhorn_matches  # noqa: F401  (import check)

    scores = rng.normal(scale=0.2 * strength, size=(rows, columns))
    source = rng.permutation(rows)[:matched]
    target = rng.permutation(columns)[:matched]
    scores[source, target] += strength
    return scores.astype(np.float32)


@pytest.mark.parametrize("strength", [2.0, 20.0, 60.0, 150.0])
@pytest.mark.parametrize("shape", [(300, 300), (400, 250), (250, 400)])
def test_float32_sinkhorn_matches_equal_the_float64_reference(shape, strength):
    from logdesc_rt.matching import sinkhorn_matches

    rng = np.random.default_rng(int(strength) + shape[0])
    scores = _structured_scores(rng, *shape, strength, matched=min(shape) * 2 // 3)
    fast = sinkhorn_matches(scores, dustbin_score=1.5, iterations=50)
    reference = mutual_matches(reference_log_assignment(scores, 1.5, 50))
    np.testing.assert_array_equal(fast.source_index, reference.source_index)
    np.testing.assert_array_equal(fast.target_index, reference.target_index)
    np.testing.assert_allclose(fast.confidence, reference.confidence, rtol=1e-4, atol=1e-6)


def test_float32_sinkhorn_equals_trainings_torch_sinkhorn():
    """Training's torch Sinkhorn and the runtime's reader agree on the same scores."""
    torch = pytest.importorskip("torch")
    from logdesc_rt.matching import sinkhorn_matches
    from training.sinkhorn import log_optimal_transport as torch_sinkhorn

    rng = np.random.default_rng(11)
    scores = _structured_scores(rng, 200, 180, 25.0, matched=120)
    torch_log_assignment = torch_sinkhorn(torch.from_numpy(scores.astype(np.float64))[None], torch.tensor(0.8), 50)[0]
    reference = mutual_matches(torch_log_assignment.numpy())
    fast = sinkhorn_matches(scores, dustbin_score=0.8, iterations=50)
    np.testing.assert_array_equal(fast.source_index, reference.source_index)
    np.testing.assert_array_equal(fast.target_index, reference.target_index)
    np.testing.assert_allclose(fast.confidence, reference.confidence, rtol=1e-4, atol=1e-6)


def test_float32_sinkhorn_threshold_and_empty_overlap():
    from logdesc_rt.matching import sinkhorn_matches

    rng = np.random.default_rng(2)
    scores = _structured_scores(rng, 100, 90, 30.0, matched=60)
    everything = sinkhorn_matches(scores, 1.0, 50)
    confident = sinkhorn_matches(scores, 1.0, 50, threshold=0.9)
    assert 0 < len(confident) < len(everything) or (everything.confidence > 0.9).all()
    assert (confident.confidence > 0.9).all()
    # Nothing resembles anything: every point goes to the dustbin, no match, no error (in the
    # paper's reading; without the dustbin in the test, ties leave at most one mutual pair).
    nothing = np.full((50, 40), -30.0, dtype=np.float32)
    assert len(sinkhorn_matches(nothing, 1.0, 50, dustbin_in_mutual_test=True)) == 0
    assert len(sinkhorn_matches(nothing, 1.0, 50)) <= 1


def test_without_the_dustbin_in_the_mutual_test_every_mutual_real_best_is_kept():
    from logdesc_rt.matching import sinkhorn_matches

    rng = np.random.default_rng(7)
    # A strong dustbin: with it in the test, most points stay unmatched.
    scores = rng.normal(scale=1.0, size=(80, 70))
    scores[np.arange(30), np.arange(30)] += 6.0  # 30 clear pairs
    with_dustbin = sinkhorn_matches(scores, 4.0, 50, dustbin_in_mutual_test=True)
    without = sinkhorn_matches(scores, 4.0, 50, dustbin_in_mutual_test=False)
    # The float32 reader and the float64 reference agree in both modes.
    reference = mutual_matches(log_optimal_transport(scores, 4.0, 50), dustbin_in_mutual_test=False)
    assert np.array_equal(without.source_index, reference.source_index)
    assert np.array_equal(without.target_index, reference.target_index)
    # Every match of the paper's test is kept, and more beside them: each real mutual best.
    assert set(zip(with_dustbin.source_index, with_dustbin.target_index)) <= set(
        zip(without.source_index, without.target_index))
    assert len(without) > len(with_dustbin)
    plan = log_optimal_transport(scores, 4.0, 50)[:-1, :-1]
    for i, j in zip(without.source_index, without.target_index):
        assert plan[i].argmax() == j and plan[:, j].argmax() == i
