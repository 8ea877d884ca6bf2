"""Do two views of one surface agree on its geometry? Shipped (paper) geometry against v3's.

    python benchmarks/geometry_agreement.py [--pairs 100] [--protocols clean noisy partial resampled ...]

For clean, noisy and noisy + partial pairs (and, on request, the resampled ones, whose clouds
share no sample) of held-out *validation* shapes (never the test split; these figures chose
v3's normals), every source point with a true counterpart in the target is compared with it,
after undoing the true rotation:

- **normal angle**: the angle between the two unit normals, sign ignored (0-90 degrees), for
  the paper's umbrella normals (area temperature 1e-4), umbrella normals at temperature 1e-2
  (the softmax then averages triangles instead of picking the largest), and v3's normal, the
  LRF's normal axis w (PCA over the 0.3-unit neighbourhood);
- **sign agreement**: how often the two views give a normal, or an LRF axis, the same sign
  (the paper geometry's rules: w away from the cloud's centroid, u toward the neighbourhood's
  centroid). v3's inputs are even in every sign, so for v3 no sign needs to agree;
- **invariant edge agreement**: the mean absolute difference between the two views' v3 edge
  channels at corresponding points, per channel group (for reference, the channels' spread).

Writes ``benchmarks/results/geometry_agreement.{md,json}``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import command_line, machine_info, validation_pairs, write_report  # noqa: E402
from logdesc_rt.config import PAPER_GEOMETRY, GeometryConfig  # noqa: E402
from logdesc_rt.geometry import compute_geometry  # noqa: E402
from logdesc_rt.geometry.normals import umbrella_normals  # noqa: E402
from logdesc_rt.normalization import PairNormalization  # noqa: E402
from logdesc_rt.synthetic import PAPER_PROTOCOLS, PROTOCOLS  # noqa: E402

PAPER = PAPER_GEOMETRY  # the paper's umbrella normals and signed LRF
V3 = GeometryConfig(edge_layout="invariant", normals="pca")
AVERAGED_UMBRELLA_TEMPERATURE = 1e-2
NORMALS = ("paper umbrella (T 1e-4)", "umbrella, T 1e-2", "v3: PCA normal (LRF w)")
# v3 edge channels grouped as in logdesc_rt/geometry/invariant_features.py.
EDGE_GROUPS = {"distance": [0], "normal angles": [1, 2, 3], "bend": [4], "point shape": [5, 6, 7], "shape differences": [8, 9, 10]}


def table_header(first_column: str, protocols: list[str]) -> list[str]:
    """The two header lines of a markdown table with one column per protocol."""
    return [f"| {first_column} | " + " | ".join(protocols) + " |", "| --- | " + " | ".join("---:" for _ in protocols) + " |"]


def pair_measurements(pair) -> dict[str, np.ndarray]:
    """Per corresponding point: unsigned normal angles (deg), sign agreements, edge differences."""
    normalization = PairNormalization.fit(pair.source, pair.target)
    source = normalization.source_to_network(pair.source)
    target = normalization.target_to_network(pair.target)
    rotation = pair.T_gt[:3, :3]
    has_match = pair.gt_match >= 0
    mine, theirs = np.flatnonzero(has_match), pair.gt_match[has_match]

    paper = compute_geometry(source, PAPER), compute_geometry(target, PAPER)
    v3 = compute_geometry(source, V3), compute_geometry(target, V3)
    averaged = [
        umbrella_normals(g.points, g.neighbour_index, g.pca.lrf, AVERAGED_UMBRELLA_TEMPERATURE) for g in paper
    ]
    normals = {
        NORMALS[0]: (paper[0].normals, paper[1].normals),
        NORMALS[1]: tuple(averaged),
        NORMALS[2]: (v3[0].normals, v3[1].normals),
    }
    out: dict[str, np.ndarray] = {}
    for name, (normals_source, normals_target) in normals.items():
        cosine = np.einsum("nc,nc->n", normals_source[mine] @ rotation.T, normals_target[theirs])
        out[f"angle/{name}"] = np.degrees(np.arccos(np.clip(np.abs(cosine), 0.0, 1.0)))
        out[f"sign/{name}"] = cosine > 0
    for axis, column in (("u", 0), ("w", 2)):
        a = paper[0].pca.lrf[mine, :, column] @ rotation.T
        b = paper[1].pca.lrf[theirs, :, column]
        out[f"sign/paper LRF {axis}"] = np.einsum("nc,nc->n", a, b) > 0
    # Edge features: the same neighbour sets are not guaranteed across views, so compare the
    # per-point channel means over the k neighbours (what a max/mean pool would see).
    pooled_source = v3[0].edges.mean(axis=1)[mine]
    pooled_target = v3[1].edges.mean(axis=1)[theirs]
    for group, channels in EDGE_GROUPS.items():
        out[f"edges/{group}"] = np.abs(pooled_source[:, channels] - pooled_target[:, channels]).mean(axis=1)
        out[f"edge_spread/{group}"] = pooled_source[:, channels].std(axis=0).mean() * np.ones(1)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=100, help="validation pairs per protocol")
    parser.add_argument("--protocols", nargs="+", default=list(PAPER_PROTOCOLS), choices=PROTOCOLS,
                        help="pair protocols (logdesc_rt.synthetic); the resampled ones share no sample")
    args = parser.parse_args(argv)

    results: dict[str, dict] = {}
    for protocol in args.protocols:
        collected: dict[str, list[np.ndarray]] = {}
        for pair in validation_pairs(protocol, args.pairs):
            for key, values in pair_measurements(pair).items():
                collected.setdefault(key, []).append(values)
        merged = {key: np.concatenate(values) for key, values in collected.items()}
        summary: dict[str, dict] = {}
        for key, values in merged.items():
            kind, name = key.split("/", 1)
            if kind == "angle":
                summary[key] = {"median_deg": float(np.median(values)), "mean_deg": float(values.mean()),
                                "p90_deg": float(np.percentile(values, 90))}
            elif kind == "sign":
                summary[key] = {"agreement": float(values.mean())}
            elif kind == "edges":
                summary[key] = {"mean_abs_difference": float(values.mean())}
            else:
                summary[key] = {"spread": float(values.mean())}
        summary["points"] = int(len(merged[f"angle/{NORMALS[0]}"]))
        results[protocol] = summary
        print(f"{protocol}: {summary['points']} corresponding points")

    protocols = list(results)
    lines = [
        "# Geometry agreement at corresponding points: the paper geometry against v3's",
        "",
        f"`{command_line()}`: {args.pairs} validation pairs per protocol (held-out training shapes, "
        "never the test split), every source point with a true counterpart.",
        "",
        "## Normal angle between the two views (degrees, sign ignored): median / mean / 90th percentile",
        "",
        *table_header("normal", protocols),
    ]
    for name in NORMALS:
        cells = [
            "{median_deg:.1f} / {mean_deg:.1f} / {p90_deg:.1f}".format(**results[p][f"angle/{name}"]) for p in protocols
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## Sign agreement between the two views (share of corresponding points)",
        "",
        *table_header("sign", protocols),
    ]
    for name in ("paper LRF u", "paper LRF w", NORMALS[0], NORMALS[2]):
        cells = [f"{100 * results[p][f'sign/{name}']['agreement']:.1f} %" for p in protocols]
        label = f"{name} normal" if name in NORMALS else name
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += [
        "| v3 inputs | " + " | ".join("not needed" for _ in protocols) + " |",
        "",
        "v3 reads only functions that are even in every normal's sign (|n_i . e|, |n_i . n_m|, "
        "(n_i . e)(n_m . e)(n_i . n_m), (n_i . n_j)^2 and ^4 in attention), so a sign that flips between "
        "views changes nothing; the LRF's u axis is not read at all.",
        "",
        "## v3 edge channels: mean |difference| of the per-point neighbour means (spread of the channel in brackets)",
        "",
        *table_header("channels", protocols),
    ]
    for group in EDGE_GROUPS:
        cells = [
            f"{results[p][f'edges/{group}']['mean_abs_difference']:.4f} ({results[p][f'edge_spread/{group}']['spread']:.3f})"
            for p in protocols
        ]
        lines.append(f"| {group} | " + " | ".join(cells) + " |")
    payload = {"command": command_line(), "pairs_per_protocol": args.pairs, "results": results, "machine": machine_info()}
    md, js = write_report("geometry_agreement", "\n".join(lines), payload)
    print("\n".join(lines))
    print(f"wrote {md} and {js}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
