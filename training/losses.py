"""Training losses on the Sinkhorn output and on the pre-transformer descriptors.

Ground truth is given per point as the index of its counterpart in the other cloud, -1 when it
has none, ``IGNORED`` (-2) when it is unlabelled (resampled pairs,
:mod:`logdesc_rt.synthetic`): ``gt_match_src`` (B, N) int64 with values in [-2, M),
``gt_match_tgt`` (B, M) in [-2, N). Ignored points add no term to any loss. The matching must
be one-to-one (``gt_match_tgt[gt_match_src[i]] == i``); :func:`invert_matches` builds
``gt_match_tgt`` from ``gt_match_src`` when that holds (without ignored points).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from logdesc_rt.metrics import IGNORED

__all__ = ["assignment_distillation", "assignment_nll", "descriptor_infonce", "invert_matches"]


def invert_matches(gt_match_src: torch.Tensor, target_count: int) -> torch.Tensor:
    """(B, N) source -> target indices (-1: none) to the (B, M) target -> source indices."""
    batch, count = gt_match_src.shape
    inverse = torch.full((batch, target_count + 1), -1, dtype=torch.long, device=gt_match_src.device)
    columns = torch.where(gt_match_src >= 0, gt_match_src, torch.full_like(gt_match_src, target_count))
    rows = torch.arange(count, device=gt_match_src.device).expand(batch, count)
    inverse.scatter_(1, columns.long(), rows)  # unmatched sources all land in the spare column
    return inverse[:, :target_count]


def _target_columns(gt_match: torch.Tensor, dustbin: int) -> torch.Tensor:
    """Replace -1 (no counterpart) by the dustbin index (and ``IGNORED``, whose terms the
    callers mask out)."""
    return torch.where(gt_match >= 0, gt_match, torch.full_like(gt_match, dustbin)).long()


def assignment_nll(
    log_assignment: torch.Tensor, gt_match_src: torch.Tensor, gt_match_tgt: torch.Tensor
) -> torch.Tensor:
    """Negative log-likelihood of the ground-truth assignment (SuperGlue / MDGAT).

    Terms, for one pair:
      * every source point i: -logP[i, gt(i)], where gt(i) is the dustbin column M when i has no
        counterpart (so this covers the matched pairs and the unmatched sources);
      * every unmatched target point j: -logP[N, j] (dustbin row).
    Matched targets add no term of their own (their pair is counted once, on the source side);
    ignored points add none at all. Averaging: the terms of a pair are averaged (divided by
    #labelled sources + #unmatched targets, MDGAT's normalisation), then pairs are averaged
    over the batch.

    Args:
        log_assignment: (B, N + 1, M + 1) from :func:`training.sinkhorn.log_optimal_transport`.
        gt_match_src: (B, N) int64 in [-2, M).
        gt_match_tgt: (B, M) int64 in [-2, N).

    Returns:
        Scalar loss.
    """
    rows, cols = log_assignment.shape[1] - 1, log_assignment.shape[2] - 1
    columns = _target_columns(gt_match_src, cols)
    source_terms = torch.gather(log_assignment[:, :rows, :], 2, columns.unsqueeze(2)).squeeze(2)
    labelled_src = (gt_match_src != IGNORED).to(log_assignment.dtype)
    unmatched_tgt = (gt_match_tgt == -1).to(log_assignment.dtype)
    target_terms = log_assignment[:, rows, :cols] * unmatched_tgt
    total = (source_terms * labelled_src).sum(dim=1) + target_terms.sum(dim=1)
    count = (labelled_src.sum(dim=1) + unmatched_tgt.sum(dim=1)).clamp(min=1.0)
    return (-total / count).mean()


INFONCE_TEMPERATURE = 0.1
"""Default softmax temperature of :func:`descriptor_infonce` (``--infonce-temperature``)."""


def descriptor_infonce(
    desc_src: torch.Tensor,
    desc_tgt: torch.Tensor,
    gt_match_src: torch.Tensor,
    temperature: float = INFONCE_TEMPERATURE,
    symmetric: bool = True,
) -> torch.Tensor:
    """Contrastive (InfoNCE) loss on the unit-norm descriptors before the transformer.

    For every ground-truth pair (i, j): cross-entropy of j among all M targets under the logits
    <desc_src_i, desc_tgt_m> / temperature, and (``symmetric``) of i among all N sources for
    target j. Averaged over all pairs of the batch (pooled). Gives the descriptor a direct
    gradient, so learning starts faster than through the transformer and Sinkhorn alone.

    Args:
        desc_src: (B, N, d) unit-norm descriptors.
        desc_tgt: (B, M, d).
        gt_match_src: (B, N) int64 in [-2, M) (only matches, >= 0, count).
        temperature: softmax temperature (cosine similarities are in [-1, 1]).
        symmetric: also the target -> source direction.

    Returns:
        Scalar loss (0, still attached to the graph, when the batch has no pair).
    """
    logits = desc_src @ desc_tgt.transpose(1, 2) / temperature  # (B, N, M)
    matched = gt_match_src >= 0
    columns = gt_match_src.clamp(min=0).long().unsqueeze(2)
    weight = matched.to(logits.dtype)
    count = weight.sum().clamp(min=1.0)

    row_log_prob = torch.gather(F.log_softmax(logits, dim=2), 2, columns).squeeze(2)
    loss = -(row_log_prob * weight).sum() / count
    if symmetric:
        col_log_prob = torch.gather(F.log_softmax(logits, dim=1), 2, columns).squeeze(2)
        loss = 0.5 * (loss - (col_log_prob * weight).sum() / count)
    return loss


def assignment_distillation(log_assignment: torch.Tensor, teacher_log_assignment: torch.Tensor) -> torch.Tensor:
    """KL divergence from a teacher's Sinkhorn assignment to the student's (distillation).

    Every real row of the assignment (a source point's distribution over the M targets and the
    dustbin) and every real column (a target's over the N sources and the dustbin) is a
    distribution (:mod:`training.sinkhorn`); the loss is KL(teacher || student) averaged over
    the N rows and, separately, the M columns, then the two halves averaged, then the batch.
    Unlike :func:`assignment_nll` it has a term for every point, labelled or not: the teacher's
    whole plan, where it is sure and where it hesitates, is the target.

    Args:
        log_assignment: (B, N + 1, M + 1) the student's, from
            :func:`training.sinkhorn.log_optimal_transport`.
        teacher_log_assignment: (B, N + 1, M + 1) the teacher's on the same pair (no gradient
            is taken through it).

    Returns:
        Scalar loss, >= 0 up to the Sinkhorn's convergence error; 0 when the plans agree.
    """
    if log_assignment.shape != teacher_log_assignment.shape:
        raise ValueError(
            f"assignment_distillation: student {tuple(log_assignment.shape)} and teacher "
            f"{tuple(teacher_log_assignment.shape)} differ"
        )
    teacher_log = teacher_log_assignment.detach()
    pointwise = teacher_log.exp() * (teacher_log - log_assignment)  # (B, N + 1, M + 1)
    rows = pointwise[:, :-1, :].sum(dim=2).mean(dim=1)  # (B,) over the N real rows
    columns = pointwise[:, :, :-1].sum(dim=1).mean(dim=1)  # (B,) over the M real columns
    return (0.5 * (rows + columns)).mean()


def soft_correspondence_distance(
    log_assignment: torch.Tensor,
    source_points: torch.Tensor,
    target_points: torch.Tensor,
    true_pose: torch.Tensor,
    gt_match_src: torch.Tensor,
) -> torch.Tensor:
    """Mean distance between each matched source point's true position in the target frame and
    the Sinkhorn plan's mean of the target points for it.

    For source point i with a counterpart (``gt_match_src[i] >= 0``), the plan's row over the M
    real targets, normalised, weights the target points: y_hat_i = sum_j P_ij y_j / sum_j P_ij.
    The term is |y_hat_i - (R x_i + t)|, averaged over all such points of the batch.
    Where :func:`assignment_nll` scores only the named target point, this charges the plan by
    how far its mass lies from the truth: mass on a neighbour of the true partner costs a
    spacing, a confusion across the object costs its distance.

    Args:
        log_assignment: (B, N + 1, M + 1) from :func:`training.sinkhorn.log_optimal_transport`.
        source_points: (B, N, 3), target_points: (B, M, 3), network units.
        true_pose: (B, 4, 4) the true source -> target pose, network frame.
        gt_match_src: (B, N) int64 in [-2, M); only points with a counterpart count.

    Returns:
        Scalar, network units; 0 for a batch without a labelled counterpart.
    """
    rows, cols = log_assignment.shape[1] - 1, log_assignment.shape[2] - 1
    plan = log_assignment[:, :rows, :cols].float().exp()  # (B, N, M)
    row_mass = plan.sum(dim=2, keepdim=True).clamp(min=1e-12)
    expected_target = plan @ target_points.float() / row_mass  # (B, N, 3)
    rotation, translation = true_pose[:, :3, :3].float(), true_pose[:, :3, 3].float()
    truth = source_points.float() @ rotation.transpose(1, 2) + translation[:, None, :]
    distance = (expected_target - truth).norm(dim=2)
    matched = (gt_match_src >= 0).to(distance.dtype)
    return (distance * matched).sum() / matched.sum().clamp(min=1.0)
