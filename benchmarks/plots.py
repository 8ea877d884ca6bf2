"""Plots shared by the benchmark scripts (matplotlib, Agg: no screen needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

# One colour and line style per method, the same in every figure.
STYLES = {
    "logdesc_fsr": ("tab:red", "-"),
    "logdesc_svd": ("tab:orange", "--"),
    "logdesc_ransac": ("tab:brown", ":"),
    "logdesc_desc_ransac": ("tab:purple", "-"),
    "logdesc_desc_fgr": ("tab:pink", "--"),
    "fpfh_ransac": ("tab:blue", "-"),
    "fpfh_fgr": ("tab:cyan", "--"),
    "icp_point_to_plane": ("tab:gray", "-."),
    "logdesc_fsr_icp": ("darkred", "-."),
    "fpfh_fgr_icp": ("navy", "-."),
}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def error_cdf(records: dict[str, dict[str, list[dict]]], path: Path, title: str, max_deg: float = 180.0) -> None:
    """Cumulative share of pairs against rotation error, one panel per group (protocol).

    Args:
        records: group -> method -> per-pair records (with ``rotation_error_deg``).
        path: PNG to write.
        title: figure title.
        max_deg: x-axis limit, degrees (log scale from 0.01).
    """
    plt = _pyplot()
    groups = list(records)
    figure, axes = plt.subplots(1, len(groups), figsize=(5.2 * len(groups), 5.0), squeeze=False)
    for axis, group in zip(axes[0], groups, strict=True):
        for method, method_records in records[group].items():
            errors = np.sort([r["rotation_error_deg"] for r in method_records])
            if len(errors) == 0:
                continue
            colour, style = STYLES.get(method, (None, "-"))
            share = np.arange(1, len(errors) + 1) / len(errors)
            axis.step(np.maximum(errors, 1e-2), share, where="post", color=colour, linestyle=style, label=method)
        axis.set_xscale("log")
        axis.set_xlim(1e-2, max_deg)
        axis.set_ylim(0, 1)
        axis.set_xlabel("rotation error L_R (degrees, log)")
        axis.set_title(group)
        axis.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("share of pairs with error <= x")
    handles, labels = axes[0][0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="lower center", ncol=min(len(labels), 5), fontsize=8)
    figure.suptitle(title)
    figure.tight_layout(rect=(0, 0.12, 1, 1))
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)
