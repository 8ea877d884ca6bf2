"""Sinkhorn with a dustbin row and column (SuperGlue's optimal transport), for training.

The algorithm, exactly (the NumPy runtime in ``logdesc_rt/matching.py`` must match it step for
step; ``tests/test_matching.py`` and ``tests/test_model.py`` compare them):

1. Couplings Z, shape (N + 1, M + 1): Z[:N, :M] = scores; the last column, the last row and the
   corner all equal the dustbin score alpha.
2. Marginals, normalised by N + M, with ``norm = -log(N + M)``:
   log_mu = [norm] * N + [log(M) + norm]   (each real row has mass 1, the dustbin row mass M),
   log_nu = [norm] * M + [log(N) + norm]   (each real column mass 1, the dustbin column mass N).
3. u = 0 (N + 1), v = 0 (M + 1); then ``iterations`` times, u first, then v:
   u = log_mu - logsumexp_j(Z[i, j] + v[j])
   v = log_nu - logsumexp_i(Z[i, j] + u[i])
4. Return Z + u[:, None] + v[None, :] - norm, i.e. the log transport plan times N + M, so that
   exp of a real row or real column sums to ~1 (columns exactly after the last v update, rows
   up to the convergence error).
"""

from __future__ import annotations

import math

import torch


def log_optimal_transport(
    scores: torch.Tensor, dustbin_score: torch.Tensor, iterations: int
) -> torch.Tensor:
    """Sinkhorn assignment with a learned dustbin (:func:`scaling_optimal_transport`), one pair
    at a time on the CPU.

    The iterations are matrix-vector products, bound by memory traffic: one pair's kernel
    (4 MB at 1024 points) is read 2 x ``iterations`` times forward and again backward, and
    stays in the CPU's cache only alone. Pair by pair, a batch of 8 x 1024 points runs about
    4x faster forward and backward than all at once, with the same values (each pair's plan
    depends on that pair only). On a GPU the whole batch goes at once.

    Args and returns: as :func:`scaling_optimal_transport`.
    """
    if scores.device.type != "cpu" or scores.shape[0] <= 1:
        return scaling_optimal_transport(scores, dustbin_score, iterations)
    return torch.cat(
        [scaling_optimal_transport(scores[i : i + 1], dustbin_score, iterations) for i in range(scores.shape[0])]
    )


def scaling_optimal_transport(
    scores: torch.Tensor, dustbin_score: torch.Tensor, iterations: int
) -> torch.Tensor:
    """Sinkhorn assignment with a learned dustbin, by scaling iterations on one kernel.

    The same plan as :func:`log_domain_optimal_transport` (the algorithm of the module
    docstring) and as the runtime's :func:`logdesc_rt.matching.sinkhorn_matches`, computed
    the way the runtime computes it:

        E = exp(Z - m), m_i = max_j Z_ij (detached: the plan does not depend on it)
        a = mu / (E b), b = nu / (E^T a), b starting at 1, ``iterations`` times
        log-assignment = Z - m + log a + log b + log(N + M)

    One exp pass and 2 x ``iterations`` batched matrix-vector products instead of
    2 x ``iterations`` log-sum-exps over (B, N+1, M+1): autograd keeps one kernel and a few
    vectors per iteration, not two full matrices per iteration. The dustbin row of E is all
    ones and every row holds a 1, so no row or column sum can underflow; if a scaling still
    leaves the finite range, the log-domain iteration answers instead.

    Args:
        scores: (B, N, M) matching scores.
        dustbin_score: scalar tensor alpha (learned), the score of matching to the dustbin.
        iterations: number of (u, v) update pairs.

    Returns:
        (B, N + 1, M + 1) log-assignment; row N is the target dustbin row, column M the source
        dustbin column. exp(out[b, i, :]).sum() ~ 1 for every real row i.
    """
    couplings, log_mu, log_nu, norm = _couplings_and_marginals(scores, dustbin_score)
    shift = couplings.detach().amax(dim=2, keepdim=True)  # (B, N+1, 1)
    kernel = torch.exp(couplings - shift)
    mu, nu = log_mu.exp(), log_nu.exp()
    column_scaling = torch.ones_like(nu)
    for _ in range(iterations):
        row_scaling = mu / (kernel @ column_scaling.unsqueeze(2)).squeeze(2)
        column_scaling = nu / (row_scaling.unsqueeze(1) @ kernel).squeeze(1)
    if not (torch.isfinite(row_scaling).all() and torch.isfinite(column_scaling).all()
            and (row_scaling > 0).all() and (column_scaling > 0).all()):
        return log_domain_optimal_transport(scores, dustbin_score, iterations)
    return couplings - shift + row_scaling.log().unsqueeze(2) + column_scaling.log().unsqueeze(1) - norm


def _couplings_and_marginals(scores: torch.Tensor, dustbin_score: torch.Tensor):
    """Z (B, N+1, M+1) with the dustbin row / column, log mu (B, N+1), log nu (B, M+1), norm."""
    batch, rows, cols = scores.shape
    if rows < 1 or cols < 1:
        raise ValueError(f"log_optimal_transport needs N, M >= 1, got scores {tuple(scores.shape)}")
    alpha = dustbin_score.to(scores).reshape(1, 1, 1)
    couplings = torch.cat(
        (
            torch.cat((scores, alpha.expand(batch, rows, 1)), dim=2),
            torch.cat((alpha.expand(batch, 1, cols), alpha.expand(batch, 1, 1)), dim=2),
        ),
        dim=1,
    )
    norm = -math.log(rows + cols)
    log_mu = torch.full((rows + 1,), norm, dtype=scores.dtype, device=scores.device)
    log_nu = torch.full((cols + 1,), norm, dtype=scores.dtype, device=scores.device)
    log_mu[rows] = math.log(cols) + norm
    log_nu[cols] = math.log(rows) + norm
    return couplings, log_mu.expand(batch, rows + 1), log_nu.expand(batch, cols + 1), norm


def log_domain_optimal_transport(
    scores: torch.Tensor, dustbin_score: torch.Tensor, iterations: int
) -> torch.Tensor:
    """Sinkhorn assignment with a learned dustbin, the textbook log-domain iteration (reference).

    Args:
        scores: (B, N, M) matching scores.
        dustbin_score: scalar tensor alpha (learned), the score of matching to the dustbin.
        iterations: number of (u, v) update pairs.

    Returns:
        (B, N + 1, M + 1) log-assignment; row N is the target dustbin row, column M the source
        dustbin column. exp(out[b, i, :]).sum() ~ 1 for every real row i.
    """
    couplings, log_mu, log_nu, norm = _couplings_and_marginals(scores, dustbin_score)
    u = torch.zeros_like(log_mu)
    v = torch.zeros_like(log_nu)
    for _ in range(iterations):
        u = log_mu - torch.logsumexp(couplings + v.unsqueeze(1), dim=2)
        v = log_nu - torch.logsumexp(couplings + u.unsqueeze(2), dim=1)
    return couplings + u.unsqueeze(2) + v.unsqueeze(1) - norm
