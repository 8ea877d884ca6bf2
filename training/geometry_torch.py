"""v3's per-point geometry in torch, batched, on the training device: a port held to NumPy.

The NumPy code in :mod:`logdesc_rt.geometry` is the single reference (the runtime runs it, and
training computes it in data-loader workers by default). On a GPU those workers cannot keep
up, so this module computes the same geometry for a whole batch on the device. It is never
edited apart from the reference: ``tests/test_geometry_torch.py`` compares the two on the same
points, channel by channel.

Only the ``"invariant"`` and ``"chiral"`` edge layouts with PCA normals (what the v3 and v4
networks read) are ported: kNN by a dense distance matrix, PCA over the radius neighbourhood,
:func:`logdesc_rt.geometry.invariant_edge_features` and
:func:`logdesc_rt.geometry.chiral_edge_channels`. Shapes: B clouds of N points.
"""

from __future__ import annotations

import torch

from logdesc_rt.config import GeometryConfig
from logdesc_rt.geometry.pca import _MIN_EIGENVALUE


def invariant_geometry(points: torch.Tensor, config: GeometryConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Edges and normals of a batch of clouds, as :func:`logdesc_rt.geometry.compute_geometry`.

    Args:
        points: (B, N, 3) positions, network units, N > config.umbrella_neighbours.
        config: an ``edge_layout="invariant"`` or ``"chiral"``, ``normals="pca"`` geometry config.

    Returns:
        edges: (B, N, k, C) float32 (the reference's C = 11 or 13 channels; k = umbrella_neighbours).
        normals: (B, N, 3) float32 unit PCA normals (signs may differ from the reference's:
            nothing downstream reads them).
    """
    if config.edge_layout not in ("invariant", "chiral") or config.normals != "pca":
        raise ValueError("the torch geometry covers the invariant and chiral layouts with PCA normals only")
    batch, count, _ = points.shape
    k = config.umbrella_neighbours
    if count <= k:
        raise ValueError(f"points: {count} per cloud, but {k} neighbours need at least {k + 1}")
    with torch.no_grad():
        # Nearest first, the point itself included (as pykdtree's query in the reference).
        squared = torch.cdist(points, points).square()
        neighbours = min(max(config.pca_max_neighbours, k + 1), count)
        squared_distance, index = torch.topk(squared, neighbours, dim=2, largest=False, sorted=True)
        distance = squared_distance.clamp_min(0.0).sqrt()

        shape_features, normals, major = _pca(points, distance, index, config)
        neighbour_index = _drop_self(index[:, :, : k + 1], k)
        edges = _invariant_edges(points, shape_features, normals, neighbour_index, config.pca_radius)
        if config.edge_layout == "chiral":
            gate = (shape_features[..., 0] - shape_features[..., 1]) * shape_features[..., 1]
            edges = torch.cat((edges, _chiral_channels(points, normals, major, gate, neighbour_index)), dim=3)
    return edges.float(), normals.float()


def _gather_points(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """values (B, N, C), index (B, N, K) -> (B, N, K, C)."""
    batch, count, neighbours = index.shape
    flat = index.reshape(batch, count * neighbours, 1).expand(-1, -1, values.shape[2])
    return torch.gather(values, 1, flat).reshape(batch, count, neighbours, values.shape[2])


def _pca(points, distance, index, config: GeometryConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(B, N, 3) anisotropy / planarity / omnivariance, (B, N, 3) PCA normals (w) and (B, N, 3)
    major axes (u)."""
    max_neighbours = config.pca_max_neighbours
    distance, index = distance[:, :, :max_neighbours], index[:, :, :max_neighbours]
    within = distance < config.pca_radius
    within[:, :, : config.pca_min_neighbours] = True
    weights = within.to(points.dtype)  # (B, N, K)
    count = weights.sum(dim=2)
    neighbour_points = _gather_points(points, index)  # (B, N, K, 3)
    mean = (weights.unsqueeze(2) @ neighbour_points).squeeze(2) / count.unsqueeze(2)
    centred = (neighbour_points - mean.unsqueeze(2)) * weights.unsqueeze(3)
    covariance = centred.transpose(2, 3) @ centred / count[..., None, None]
    eigenvalues, eigenvectors = torch.linalg.eigh(covariance)  # ascending
    eigenvalues = eigenvalues.clamp_min(0.0)
    l3, l2, l1 = eigenvalues.unbind(dim=2)
    has_shape = l1 > _MIN_EIGENVALUE
    safe_l1 = torch.where(has_shape, l1, torch.ones_like(l1))
    anisotropy = torch.where(has_shape, (l1 - l3) / safe_l1, torch.zeros_like(l1))
    planarity = torch.where(has_shape, (l2 - l3) / safe_l1, torch.zeros_like(l1))
    omnivariance = (l1 * l2 * l3).clamp_min(0.0).pow(1.0 / 3.0)
    normals = eigenvectors[:, :, :, 0]
    # The reference gives shapeless neighbourhoods the identity LRF: w = z.
    normals = torch.where(has_shape.unsqueeze(2), normals, torch.tensor([0.0, 0.0, 1.0]).to(normals))
    major = torch.where(has_shape.unsqueeze(2), eigenvectors[:, :, :, 2], torch.tensor([1.0, 0.0, 0.0]).to(normals))
    return torch.stack((anisotropy, planarity, omnivariance), dim=2), normals, major


def _drop_self(index: torch.Tensor, k: int) -> torch.Tensor:
    """(B, N, k + 1) self-inclusive neighbours -> (B, N, k) others, as ``drop_self`` does:
    the query point is removed wherever it is listed; where it is not (more than k exact
    duplicates), the farthest entry goes."""
    batch, count, _ = index.shape
    is_self = index == torch.arange(count, device=index.device).reshape(1, count, 1)
    is_self[..., -1] |= ~is_self.any(dim=2)
    # A stable sort on the flag moves the one dropped entry last, keeping the others' order.
    order = torch.sort(is_self.to(torch.uint8), dim=2, stable=True).indices
    return torch.gather(index, 2, order)[:, :, :k]


def _invariant_edges(points, shape_features, normals, neighbour_index, length_scale: float) -> torch.Tensor:
    """The (B, N, k, 11) channels of :mod:`logdesc_rt.geometry.invariant_features`."""
    offsets = _gather_points(points, neighbour_index) - points.unsqueeze(2)  # (B, N, k, 3)
    distance = offsets.norm(dim=3)
    direction = offsets / torch.where(distance > 0.0, distance, torch.ones_like(distance)).unsqueeze(3)
    neighbour_normals = _gather_points(normals, neighbour_index)
    normal_i_offset = (direction * normals.unsqueeze(2)).sum(dim=3)
    normal_m_offset = (direction * neighbour_normals).sum(dim=3)
    normal_i_normal_m = (neighbour_normals * normals.unsqueeze(2)).sum(dim=3)
    scale = torch.tensor([1.0, 1.0, 1.0 / length_scale**2]).to(shape_features)
    scaled_shape = shape_features * scale
    point_shape = scaled_shape.unsqueeze(2).expand(-1, -1, neighbour_index.shape[2], -1)
    return torch.cat(
        (
            (distance / length_scale).unsqueeze(3),
            normal_i_offset.abs().unsqueeze(3),
            normal_m_offset.abs().unsqueeze(3),
            normal_i_normal_m.abs().unsqueeze(3),
            (normal_i_offset * normal_m_offset * normal_i_normal_m).unsqueeze(3),
            point_shape,
            _gather_points(scaled_shape, neighbour_index) - point_shape,
        ),
        dim=3,
    )


def _cbrt(values: torch.Tensor) -> torch.Tensor:
    """Real cube root, odd like NumPy's ``cbrt``."""
    return values.sign() * values.abs().pow(1.0 / 3.0)


def _chiral_channels(points, normals, major, gate, neighbour_index) -> torch.Tensor:
    """The (B, N, k, 2) reflection-odd channels of :func:`logdesc_rt.geometry.chiral_edge_channels`."""
    offsets = _gather_points(points, neighbour_index) - points.unsqueeze(2)
    distance = offsets.norm(dim=3)
    direction = offsets / torch.where(distance > 0.0, distance, torch.ones_like(distance)).unsqueeze(3)
    neighbour_normals = _gather_points(normals, neighbour_index)
    point_normals = normals.unsqueeze(2).expand_as(neighbour_normals)
    normal_i_offset = (direction * point_normals).sum(dim=3)
    normal_m_offset = (direction * neighbour_normals).sum(dim=3)
    twist = (torch.linalg.cross(point_normals, neighbour_normals, dim=3) * direction).sum(dim=3)
    octant = (
        (direction * torch.linalg.cross(major, normals, dim=2).unsqueeze(2)).sum(dim=3)
        * (direction * major.unsqueeze(2)).sum(dim=3)
        * (direction * normals.unsqueeze(2)).sum(dim=3)
    )
    return torch.stack(
        (_cbrt(twist * normal_i_offset * normal_m_offset), _cbrt(gate.unsqueeze(2) * octant)), dim=3
    )
