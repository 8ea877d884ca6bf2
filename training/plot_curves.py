"""Plot a training log (``log.jsonl`` of :mod:`training.train`) against wall time.

Usage::

    python -m training.plot_curves runs/small/log.jsonl runs/small/curves.png [--smooth 50]

Panels (x axis: accumulated training wall time, hours or minutes):

1. training loss (and its terms), raw and smoothed, with the validation loss;
2. validation matching precision / accuracy / recall of the mutual matches;
3. validation rotation error L_R (median and mean, degrees, log scale);
4. learning rate.

Lines of a resumed run's log are read in order; the wall time already accumulates across
sessions in the log itself. Where a resumed run changed the pairs it trains and validates on
(``--any-orientation``), a vertical line marks the change on every panel: validation figures
on either side of it are measured on different pairs.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only: no display needed (servers, CI)
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def pair_protocol(args: dict) -> str:
    """How a run drew its pairs, from the ``args`` of its start / resume record."""
    return "any orientation" if args.get("any_orientation") else "upright pairs (paper protocol)"


def read_log_segments(path) -> tuple[list[dict], list[dict], list[tuple[float, str]]]:
    """(train records, val records, changes) of a log, skipping lines cut by a crash.

    ``changes`` lists (wall time in s, pair protocol) at the start of the log and wherever a
    resumed run's :func:`pair_protocol` differs from the run before it.
    """
    train, val, changes = [], [], []
    for line in Path(path).read_text().splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue
        if record.get("type") == "train":
            train.append(record)
        elif record.get("type") == "val":
            val.append(record)
        elif record.get("type") in ("start", "resume"):
            protocol = pair_protocol(record.get("args") or {})
            if not changes or changes[-1][1] != protocol:
                changes.append((float(record.get("wall_time_s") or 0.0), protocol))
    return train, val, changes


def smooth(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average (window clipped at the start), NaNs ignored."""
    if window <= 1 or len(values) == 0:
        return values
    finite = np.isfinite(values)
    cumulative = np.concatenate([[0.0], np.cumsum(np.where(finite, values, 0.0))])
    counts = np.concatenate([[0], np.cumsum(finite)])
    index = np.arange(1, len(values) + 1)
    start = np.maximum(0, index - window)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (cumulative[index] - cumulative[start]) / (counts[index] - counts[start])


def _column(records: list[dict], key: str) -> np.ndarray:
    return np.array([np.nan if r.get(key) is None else float(r[key]) for r in records], dtype=np.float64)


def plot_curves(log_path, out_path, smooth_window: int = 50, title: str | None = None) -> Path:
    """Render the figure; returns the output path."""
    train, val, changes = read_log_segments(log_path)
    if not train and not val:
        raise ValueError(f"{log_path}: no train or val records")
    all_times = _column(train + val, "wall_time_s")
    hours = np.nanmax(all_times) > 2 * 3600
    scale, unit = (3600.0, "h") if hours else (60.0, "min")

    figure, axes = plt.subplots(2, 2, figsize=(13, 8.5), constrained_layout=True)
    loss_axis, match_axis, rot_axis, lr_axis = axes.ravel()
    train_time = _column(train, "wall_time_s") / scale
    val_time = _column(val, "wall_time_s") / scale

    if train:
        loss = _column(train, "loss")
        loss_axis.plot(train_time, loss, color="tab:blue", alpha=0.2, linewidth=0.8)
        loss_axis.plot(train_time, smooth(loss, smooth_window), color="tab:blue", label="train loss")
        for key, color in (("nll", "tab:cyan"), ("infonce", "tab:purple"), ("gap", "tab:olive")):
            values = _column(train, key)
            if np.isfinite(values).any():
                loss_axis.plot(train_time, smooth(values, smooth_window), color=color, linewidth=1,
                               linestyle="--", label=f"train {key}")
        lr_axis.plot(train_time, _column(train, "lr"), color="tab:gray")
    if val:
        loss_axis.plot(val_time, _column(val, "val_loss"), "o-", color="tab:red", markersize=3, label="val NLL")
        for key, color in (("val_precision", "tab:green"), ("val_accuracy", "tab:orange"), ("val_recall", "tab:blue")):
            match_axis.plot(val_time, 100 * _column(val, key), "o-", markersize=3, color=color,
                            label=key.removeprefix("val_"))
        for key, style in (("val_rot_median_deg", "o-"), ("val_rot_mean_deg", "s--")):
            rot_axis.plot(val_time, _column(val, key), style, markersize=3, label=key.removeprefix("val_"))
        for protocol, color in (("clean", "tab:green"), ("noisy", "tab:orange"), ("partial", "tab:red")):
            values = _column(val, f"val_{protocol}_rot_median_deg")
            if np.isfinite(values).any():
                rot_axis.plot(val_time, values, ":", color=color, linewidth=1, label=f"{protocol} median")

    loss_axis.set(title="loss", xlabel=f"wall time ({unit})", ylabel="loss")
    match_axis.set(title="validation matching (mutual matches)", xlabel=f"wall time ({unit})", ylabel="%")
    rot_axis.set(title="validation rotation error L_R (FSR)", xlabel=f"wall time ({unit})", ylabel="degrees")
    lr_axis.set(title="learning rate", xlabel=f"wall time ({unit})", ylabel="lr")
    if val and np.nanmin(_column(val, "val_rot_median_deg")) > 0:
        rot_axis.set_yscale("log")
    for axis in (loss_axis, match_axis, rot_axis):
        if axis.get_legend_handles_labels()[0]:
            axis.legend(fontsize=8)
        axis.grid(alpha=0.3)
    lr_axis.grid(alpha=0.3)
    for wall_time, protocol in changes[1:]:  # the first entry is the log's start
        for axis in (loss_axis, match_axis, rot_axis, lr_axis):
            axis.axvline(wall_time / scale, color="black", linestyle=":", linewidth=1)
        loss_axis.annotate(f"from here: {protocol}", (wall_time / scale, 0.97), xycoords=("data", "axes fraction"),
                           xytext=(4, 0), textcoords="offset points", fontsize=8, va="top")
    if train:
        last = train[-1]
        figure.suptitle(
            title or f"{Path(log_path).parent.name}: step {last['step']}, "
            f"{last['pairs_seen']} pairs, {last['wall_time_s'] / 3600:.2f} h"
        )
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out_path, dpi=120)
    plt.close(figure)
    return out_path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m training.plot_curves", description=__doc__.split("\n")[0])
    parser.add_argument("log", type=Path, help="log.jsonl written by training.train")
    parser.add_argument("out", type=Path, help="output image (.png)")
    parser.add_argument("--smooth", type=int, default=50, help="moving-average window (train steps)")
    parser.add_argument("--title", default=None)
    args = parser.parse_args(argv)
    print(plot_curves(args.log, args.out, args.smooth, args.title))
    return 0


if __name__ == "__main__":
    sys.exit(main())
