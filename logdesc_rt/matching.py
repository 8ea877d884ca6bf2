"""Soft assignment between two clouds' descriptors: log-domain Sinkhorn with a dustbin.

SuperGlue's formulation (also MDGAT's and LoGDesc's): the N x M score matrix is augmented
with a dustbin row and column holding one learned score alpha, and Sinkhorn iterations make
the transport plan meet the marginals

    rows:    1 for each of the N source points, M for the dustbin row,
    columns: 1 for each of the M target points, N for the dustbin column,

all divided by N + M. The returned log-assignment is shifted by log(N + M), so that each
real row (and column) of exp(log_assignment) sums to 1: entry (i, j) reads as the probability
that source point i matches target point j, and column M as "i has no counterpart".

The runtime reads its matches with :func:`sinkhorn_matches`: float32 scaling iterations on one
kernel, no log-assignment matrix. :func:`log_optimal_transport` is the float64 reference it is
tested against (and falls back to, should a float32 scaling ever leave its safe range): the
textbook log-domain iteration (logsumexp, :func:`log_domain_sinkhorn`), exact for any score
range. Training's torch Sinkhorn (``training/sinkhorn.py``) is held to both by the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

from .config import MatchingConfig

_DEFAULTS = MatchingConfig()  # one home for the defaults below

def _augmented_scores(scores: np.ndarray, dustbin_score: float, dtype=np.float64) -> np.ndarray:
    """(N, M) scores -> (N+1, M+1) ``dtype`` with the dustbin row and column set to alpha."""
    scores = np.asarray(scores)
    if not np.issubdtype(scores.dtype, np.number) or np.issubdtype(scores.dtype, np.complexfloating):
        raise ValueError(f"scores: dtype {scores.dtype} is not real")
    if scores.ndim != 2 or min(scores.shape) < 1:
        raise ValueError(f"scores: shape {scores.shape} is not (N, M) with N, M >= 1")
    if not np.isfinite(scores).all():
        raise ValueError("scores: contains NaN or inf")
    if not np.isfinite(dustbin_score):
        raise ValueError(f"dustbin_score: {dustbin_score} is not finite")
    rows, columns = scores.shape
    augmented = np.full((rows + 1, columns + 1), float(dustbin_score), dtype=dtype)
    augmented[:rows, :columns] = scores
    return augmented


def _log_marginals(rows: int, columns: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Log row marginals (N+1,), log column marginals (M+1,), and log(N + M)."""
    log_total = float(np.log(rows + columns))
    log_row = np.full(rows + 1, -log_total)
    log_row[-1] = np.log(columns) - log_total
    log_column = np.full(columns + 1, -log_total)
    log_column[-1] = np.log(rows) - log_total
    return log_row, log_column, log_total


def log_optimal_transport(scores, dustbin_score: float, iterations: int = _DEFAULTS.sinkhorn_iterations) -> np.ndarray:
    """Sinkhorn-normalised log-assignment with a dustbin.

    Args:
        scores: (N, M) similarity scores (the network's <f_i, h_j> / sqrt(d)).
        dustbin_score: the learned dustbin score alpha (stored in the model file).
        iterations: Sinkhorn iterations (row then column update each).

    Returns:
        (N+1, M+1) float64 log-assignment; exp of each real row sums to 1 once converged.
    """
    if iterations < 1:
        raise ValueError(f"iterations: {iterations} < 1")
    augmented = _augmented_scores(scores, dustbin_score)
    rows, columns = augmented.shape[0] - 1, augmented.shape[1] - 1
    log_row, log_column, log_total = _log_marginals(rows, columns)

    log_u, log_v = log_domain_sinkhorn(augmented, log_row, log_column, iterations)
    return augmented + log_u[:, None] + log_v[None, :] + log_total


def log_domain_sinkhorn(
    augmented: np.ndarray, log_row: np.ndarray, log_column: np.ndarray, iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    """The textbook log-domain iteration; returns the dual potentials (u (N+1,), v (M+1,))."""
    log_v = np.zeros(augmented.shape[1])
    for _ in range(iterations):
        log_u = log_row - logsumexp(augmented + log_v[None, :], axis=1)
        log_v = log_column - logsumexp(augmented + log_u[:, None], axis=0)
    return log_u, log_v


def sinkhorn_matches(
    scores,
    dustbin_score: float,
    iterations: int = _DEFAULTS.sinkhorn_iterations,
    threshold: float = _DEFAULTS.match_threshold,
    dustbin_in_mutual_test: bool = _DEFAULTS.dustbin_in_mutual_test,
) -> "Matches":
    """Mutual best matches of the Sinkhorn assignment, read without any log-assignment matrix.

    The same transport plan as :func:`log_optimal_transport` (and as training's torch
    Sinkhorn), computed in float32 by scaling iterations on one kernel:

        E_ij = exp(Z_ij - max_j' Z_ij')        (one exp pass; every row's largest entry is 1)
        P_ij = a_i E_ij b_j,   a = mu / (E b),   b = nu / (E^T a),   b starts at 1,

    which are the log-domain updates u = log a - max_j Z_ij, v = log b written with
    matrix-vector products. The dustbin row of E is all ones (its entries all equal alpha), so
    no column sum can underflow, and every row holds its maximum 1, so no row sum can either.
    Row i's best column is argmax_j E_ij b_j and column j's best row argmax_i a_i E_ij b_j:
    both read from the kernel in place. If a scaling ever leaves float32's safe range (it has
    not on any score matrix we have seen), the float64 log-domain path answers instead.

    Args:
        scores: (N, M) similarity scores (the network's <f_i, h_j> / sqrt(d)).
        dustbin_score: the learned dustbin score alpha.
        iterations: Sinkhorn iterations (row then column update each), as in training.
        threshold: keep matches whose probability exceeds this.
        dustbin_in_mutual_test: see :class:`~logdesc_rt.config.MatchingConfig`.

    Returns:
        :class:`Matches`, as :func:`mutual_matches` of :func:`log_optimal_transport` gives
        them (up to float32 round-off in near-ties).
    """
    if iterations < 1:
        raise ValueError(f"iterations: {iterations} < 1")
    # float32 from the start: the network's scores are float32, and a float64 copy of the
    # (N+1) x (M+1) matrix cost a third of this function's time.
    augmented = _augmented_scores(scores, dustbin_score, np.float32)
    rows, columns = augmented.shape[0] - 1, augmented.shape[1] - 1
    log_row, log_column, _ = _log_marginals(rows, columns)
    row_marginal = np.exp(log_row).astype(np.float32)
    column_marginal = np.exp(log_column).astype(np.float32)

    kernel = augmented
    kernel -= kernel.max(axis=1, keepdims=True)
    np.exp(kernel, out=kernel)
    column_scaling = np.ones(columns + 1, dtype=np.float32)
    for _ in range(iterations):
        row_scaling = row_marginal / (kernel @ column_scaling)
        column_scaling = column_marginal / (row_scaling @ kernel)
    if not (_is_safe(row_scaling) and _is_safe(column_scaling)):
        return mutual_matches(log_optimal_transport(scores, dustbin_score, iterations), threshold,
                              dustbin_in_mutual_test)

    # Without the dustbin in the test, the argmaxes run over the real rows / columns only.
    kept_rows, kept_columns = (rows + 1, columns + 1) if dustbin_in_mutual_test else (rows, columns)
    kernel *= column_scaling[None, :]  # E_ij b_j: row-wise proportional to the plan
    best_column = kernel[:rows, :kept_columns].argmax(axis=1)
    kernel *= row_scaling[:, None]  # a_i E_ij b_j = P_ij, the plan itself
    best_row = kernel[:kept_rows, :columns].argmax(axis=0)
    source_index = np.flatnonzero(best_column < columns)
    target_index = best_column[source_index]
    mutual = best_row[target_index] == source_index
    source_index, target_index = source_index[mutual], target_index[mutual]
    # The log-assignment is log P + log(N + M): a real row of exp sums to 1.
    confidence = kernel[source_index, target_index].astype(np.float64) * (rows + columns)
    keep = confidence > threshold
    return Matches(
        source_index=source_index[keep].astype(np.int64),
        target_index=target_index[keep].astype(np.int64),
        confidence=confidence[keep],
    )


def _is_safe(scaling: np.ndarray) -> bool:
    """Finite, positive and far from float32's limits (so products with E stay exact enough)."""
    return bool(np.isfinite(scaling).all() and (scaling > 1e-30).all() and (scaling < 1e30).all())


@dataclass(frozen=True)
class Matches:
    """Mutual best matches read off a log-assignment.

    Attributes:
        source_index: (K,) int64 indices into the source cloud.
        target_index: (K,) int64 indices into the target cloud.
        confidence: (K,) float64 assignment probabilities in (0, 1].
    """

    source_index: np.ndarray
    target_index: np.ndarray
    confidence: np.ndarray

    def __len__(self) -> int:
        return len(self.source_index)


def mutual_matches(
    log_assignment: np.ndarray,
    threshold: float = _DEFAULTS.match_threshold,
    dustbin_in_mutual_test: bool = _DEFAULTS.dustbin_in_mutual_test,
) -> Matches:
    """Source point i matches target point j when each is the other's best, dustbin included
    (or, with ``dustbin_in_mutual_test=False``, among the real points only).

    Args:
        log_assignment: (N+1, M+1) from :func:`log_optimal_transport`.
        threshold: keep matches whose probability exp(log_assignment[i, j]) exceeds this.
        dustbin_in_mutual_test: see :class:`~logdesc_rt.config.MatchingConfig`.

    Returns:
        :class:`Matches`, sorted by source index. With the dustbin in the test, a point whose
        best entry is the dustbin is unmatched.
    """
    rows, columns = log_assignment.shape[0] - 1, log_assignment.shape[1] - 1
    kept_rows, kept_columns = (rows + 1, columns + 1) if dustbin_in_mutual_test else (rows, columns)
    best_column = log_assignment[:rows, :kept_columns].argmax(axis=1)  # (N,), == columns: dustbin
    best_row = log_assignment[:kept_rows, :columns].argmax(axis=0)  # (M,), == rows: dustbin
    source_index = np.flatnonzero(best_column < columns)
    target_index = best_column[source_index]
    mutual = best_row[target_index] == source_index
    source_index, target_index = source_index[mutual], target_index[mutual]
    confidence = np.exp(log_assignment[source_index, target_index])
    keep = confidence > threshold
    return Matches(
        source_index=source_index[keep].astype(np.int64),
        target_index=target_index[keep].astype(np.int64),
        confidence=confidence[keep],
    )


def matches_as_array(matches: Matches, source_count: int) -> np.ndarray:
    """(N,) int64: the matched target index of every source point, -1 where unmatched."""
    return correspondences_as_array(np.stack([matches.source_index, matches.target_index], axis=1), source_count)


def correspondences_as_array(correspondences: np.ndarray, source_count: int) -> np.ndarray:
    """(N,) int64 from (K, 2) rows [source index, target index]: the matched target index of
    every source point, -1 where unmatched (``RegistrationResult.correspondences`` in, the
    form the matching metrics read out)."""
    correspondences = np.asarray(correspondences, dtype=np.int64).reshape(-1, 2)
    assignment = np.full(source_count, -1, dtype=np.int64)
    assignment[correspondences[:, 0]] = correspondences[:, 1]
    return assignment


def mutual_nearest_descriptors(source_descriptors: np.ndarray, target_descriptors: np.ndarray) -> Matches:
    """Mutual nearest neighbours in descriptor space: source i and target j match when each is
    the other's most similar (cosine) descriptor. The paper's descriptor + RANSAC reading, which
    leans on the descriptor alone and so fails differently from the matcher's transformer.

    Args:
        source_descriptors, target_descriptors: (N, d) / (M, d) unit-norm descriptors (the
            descriptor network's output; :attr:`PairMatches.source_descriptors`).

    Returns:
        :class:`Matches` sorted by source index; ``confidence`` is the cosine similarity,
        clipped to [0, 1] (the estimators weigh with it).
    """
    similarity = np.asarray(source_descriptors, dtype=np.float32) @ np.asarray(target_descriptors, dtype=np.float32).T
    best_target = similarity.argmax(axis=1)  # (N,)
    best_source = similarity.argmax(axis=0)  # (M,)
    source_index = np.flatnonzero(best_source[best_target] == np.arange(len(best_target)))
    target_index = best_target[source_index]
    return Matches(
        source_index=source_index.astype(np.int64),
        target_index=target_index.astype(np.int64),
        confidence=np.clip(similarity[source_index, target_index], 0.0, 1.0).astype(np.float64),
    )
