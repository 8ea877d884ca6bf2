"""Choose Open3D's parameters for the baselines on validation pairs (never the test split).

The peers deserve parameters that suit this data, chosen the way a careful user would:
on held-out *training* shapes (the training run's validation split), every protocol, one
setting for all. For FPFH + RANSAC / FGR we sweep Open3D's voxel size v (normals within
2 v, FPFH within 5 v, RANSAC inliers 1.5 v, FGR 0.5 v; network units, object radius = 1) and
for ICP its correspondence distance. The criterion is the success rate (rotation error
< 5 deg and translation error < 5 % of the radius) over all validation pairs, ties broken by
the median rotation error. The descriptor-only logdesc methods use the same estimator
parameters as FPFH (same Open3D RANSAC / FGR, only the descriptors differ).

    python benchmarks/tune_open3d.py [--pairs 20]
    python benchmarks/tune_open3d.py --protocols resampled_partial --out benchmarks/results/modelnet10_resampled
    python benchmarks/tune_open3d.py --protocols scan --pairs 40 --out benchmarks/results/open3d_tuning_scans

``scan`` sweeps raw simulated range-scan pairs of v4's *validation* shapes
(``scan_pairs.protocol_pairs("val", "scan", n)``: ``training.data.split_train_val_test``, never
its test names), with smaller voxels added (raw views are denser than 1024-point shapes): the
parameters for range scans, simulated and real (``scan_pairs.py`` and ``bunny.py`` read them
through ``methods.SCAN_TUNING_FILE``).

Writes benchmarks/results/open3d_tuning.md and .json (``chosen`` is read by methods.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from common import command_line, machine_info, pair_record, summarize, validation_pairs, write_report  # noqa: E402
from methods import TUNING_FILE, FpfhParameters, MethodRunner  # noqa: E402
from tqdm import tqdm  # noqa: E402

from logdesc_rt.scan_simulation import SCAN_PROTOCOL  # noqa: E402
from logdesc_rt.synthetic import PAPER_PROTOCOLS  # noqa: E402
from logdesc_rt.synthetic import PROTOCOLS as SYNTHETIC_PROTOCOLS  # noqa: E402

VOXELS = (0.04, 0.06, 0.08, 0.1, 0.13, 0.16, 0.2)
SCAN_VOXELS = (0.02, 0.03, *VOXELS)  # raw views hold ~300-3000 points, up to 3x a shape's 1024
ICP_DISTANCES = (0.05, 0.1, 0.2, 0.3, 0.5)
PROTOCOLS = PAPER_PROTOCOLS  # the default sweep


def score(metrics: dict) -> tuple[float, float]:
    return (metrics["success"], -metrics["l_r_median"])


def choose(rows: dict[str, dict]) -> FpfhParameters:
    """The parameters the sweep's measurements select (``rows``: label -> summary with
    "method", "value", "success", "l_r_median"): one voxel for both FPFH estimators, the one
    whose better estimator scores best, and the best ICP distance."""

    def best(method: str) -> dict:
        return max((row for row in rows.values() if row["method"] == method), key=score)

    best_voxel = max((best("fpfh_ransac"), best("fpfh_fgr")), key=score)["value"]
    return FpfhParameters(voxel=best_voxel, icp_distance=best("icp_point_to_plane")["value"])


def tuning_pairs(protocol: str, count: int) -> list:
    """``count`` validation pairs of a protocol: raw simulated scans of v4's validation shapes for
    ``"scan"``, else the shape protocol's pairs of the held-out training shapes."""
    if protocol == SCAN_PROTOCOL:
        from scan_pairs import protocol_pairs

        return list(protocol_pairs("val", SCAN_PROTOCOL, count))
    return validation_pairs(protocol, count)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=20, help="validation pairs per protocol")
    parser.add_argument("--protocols", nargs="+", default=list(PROTOCOLS),
                        choices=(*SYNTHETIC_PROTOCOLS, SCAN_PROTOCOL),
                        help="validation protocols to tune on (default: the paper's)")
    parser.add_argument("--out", type=Path, default=TUNING_FILE.parent,
                        help="folder for open3d_tuning.{md,json}; the default one is what methods.py reads")
    args = parser.parse_args(argv)

    pairs = [pair for protocol in args.protocols for pair in tuning_pairs(protocol, args.pairs)]
    voxels = SCAN_VOXELS if SCAN_PROTOCOL in args.protocols else VOXELS
    rows: dict[str, dict] = {}
    sweeps = [("fpfh", voxel, FpfhParameters(voxel=voxel), ("fpfh_ransac", "fpfh_fgr")) for voxel in voxels]
    sweeps += [("icp", distance, FpfhParameters(icp_distance=distance), ("icp_point_to_plane",))
               for distance in ICP_DISTANCES]
    for kind, value, parameters, methods in tqdm(sweeps, desc="settings", unit="setting"):
        runner = MethodRunner(methods, parameters)
        records = {method: [] for method in methods}
        for pair in pairs:
            for method, result in runner.run(pair.source, pair.target, seed=pair.index).items():
                records[method].append(pair_record(pair, method, result))
        for method, method_records in records.items():
            label = f"{method} v={value}" if kind == "fpfh" else f"{method} d={value}"
            rows[label] = {"kind": kind, "value": value, "method": method, **summarize(method_records)}

    parameters = choose(rows)
    best_voxel, best_icp = parameters.voxel, parameters.icp_distance
    chosen = dataclasses.asdict(parameters)

    from common import markdown_table

    table = markdown_table({label: row for label, row in rows.items()}, label="setting")
    markdown = "\n".join([
        "# Open3D parameters for the baselines, chosen on validation pairs",
        "",
        f"Pairs: {args.pairs} per protocol ({', '.join(args.protocols)}) from the held-out training shapes "
        "(never the ModelNet10 test split"
        + ("; scan pairs: v4's validation split of the dense shapes, never its test names"
           if SCAN_PROTOCOL in args.protocols else "")
        + "). Units: network units (object radius = 1).",
        f"Command: `{command_line()}`. Machine: {machine_info()}.",
        "",
        f"**Chosen:** voxel v = {best_voxel} (normals 2v, FPFH 5v, RANSAC 1.5v, FGR 0.5v), "
        f"ICP distance = {best_icp}. Criterion: success rate (L_R < 5 deg, translation < 5 % of "
        "the radius), then median L_R.",
        "",
        table,
    ])
    payload = {"chosen": chosen, "pairs_per_protocol": args.pairs, "protocols": list(args.protocols),
               "command": command_line(), "machine": machine_info(), "rows": rows}
    md, js = write_report(TUNING_FILE.stem, markdown, payload, args.out)
    print(markdown)
    print(f"wrote {md} and {js}")
    return 0 if np.isfinite(best_voxel) else 1


if __name__ == "__main__":
    sys.exit(main())
