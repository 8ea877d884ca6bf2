"""Two runs' training loss side by side, per protocol, against the pairs each has seen.

Usage (from the repository root)::

    python -m training.learning_by_pairs RUN_A/log.jsonl RUN_B/log.jsonl \
        --labels a b --since-step 0 2475 --bin 16000 --out runs/learning_by_pairs.md

Why: a run that trails another on validation may be a worse model or just a younger one.
Counting pairs from where each run's task began (``--since-step``: e.g. the step at which a
run was fine-tuned onto a new task) and putting the assignment NLL of the same protocol side by
side tells the two apart: equal
losses at equal pairs say the younger run is on the same path, only earlier on it.

The NLL is each run's own logged training loss on its own random pairs (``training.train``
logs one step in ``--log-every``), so a bin holds a sample of steps; the table gives how many.
Runs differ in batch size, learning rate and model; the comparison is of pairs seen, which is
what the CPU limits, not of steps.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

if __package__ in (None, ""):  # run as ``python training/learning_by_pairs.py``: import from the repo root
    _here = Path(__file__).resolve().parent
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _here]
    sys.path.insert(0, str(_here.parent))

from training.provenance import read_log  # noqa: E402

__all__ = ["nll_by_pairs", "comparison_markdown"]


def nll_by_pairs(records: list[dict], since_step: int, bin_pairs: int) -> dict[str, dict[int, tuple[float, int]]]:
    """Mean training NLL per protocol in bins of pairs seen since ``since_step``.

    Args:
        records: a training log's records (:func:`training.provenance.read_log`).
        since_step: the step where the run's task began; earlier steps are left out and pairs
            are counted from that step's ``pairs_seen``.
        bin_pairs: width of a bin, in pairs.

    Returns:
        protocol -> {bin start (pairs since ``since_step``): (mean NLL, logged steps)}.
    """
    train = [r for r in records if r.get("type") == "train" and r["step"] > since_step]
    if not train:
        raise ValueError(f"no training records after step {since_step}")
    at_start = [r["pairs_seen"] for r in records if r.get("type") == "train" and r["step"] <= since_step]
    origin = max(at_start) if at_start else 0
    sums: dict[str, dict[int, list[float]]] = defaultdict(lambda: defaultdict(list))
    for record in train:
        start = (record["pairs_seen"] - origin) // bin_pairs * bin_pairs
        sums[record.get("protocol", "all")][start].append(float(record["nll"]))
    return {
        protocol: {start: (sum(values) / len(values), len(values)) for start, values in sorted(bins.items())}
        for protocol, bins in sums.items()
    }


def comparison_markdown(runs: dict[str, dict[str, dict[int, tuple[float, int]]]], bin_pairs: int,
                        protocols: list[str], command: str) -> str:
    """One table per protocol: rows are bins of pairs, columns the runs' mean NLL (steps)."""
    labels = list(runs)
    lines = [
        "# Training loss against pairs seen",
        "",
        f"`{command}`",
        "",
        "Mean assignment NLL of the logged training steps of each protocol, in bins of "
        f"{bin_pairs:,} pairs counted from where each run's task began (module docstring); "
        "in brackets, how many logged steps the mean is over. A dash: the run has no such step.",
    ]
    for protocol in protocols:
        if not any(protocol in runs[label] for label in labels):
            continue
        starts = sorted({start for label in labels for start in runs[label].get(protocol, {})})
        lines += ["", f"## {protocol}", "", "| pairs seen | " + " | ".join(labels) + " |",
                  "| ---: | " + " | ".join("---:" for _ in labels) + " |"]
        for start in starts:
            cells = []
            for label in labels:
                value = runs[label].get(protocol, {}).get(start)
                cells.append("-" if value is None else f"{value[0]:.2f} ({value[1]})")
            lines.append(f"| {start:,}-{start + bin_pairs:,} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("logs", nargs="+", type=Path, help="training logs (log.jsonl)")
    parser.add_argument("--labels", nargs="+", required=True, help="one name per log")
    parser.add_argument("--since-step", nargs="+", type=int, default=None,
                        help="per log, the step where its task began (default 0 for each)")
    parser.add_argument("--bin", type=int, default=16000, help="bin width in pairs")
    parser.add_argument("--protocols", nargs="+",
                        default=["clean", "noisy", "partial", "resampled", "resampled_partial"])
    parser.add_argument("--out", type=Path, default=None, help="markdown file (default: print)")
    args = parser.parse_args(argv)
    since = args.since_step or [0] * len(args.logs)
    if not len(args.logs) == len(args.labels) == len(since):
        parser.error("give one --labels and one --since-step value per log")
    runs = {
        label: nll_by_pairs(read_log(log), step, args.bin)
        for log, label, step in zip(args.logs, args.labels, since, strict=True)
    }
    command = "python -m training.learning_by_pairs " + " ".join(argv if argv is not None else sys.argv[1:])
    text = comparison_markdown(runs, args.bin, args.protocols, command)
    if args.out is None:
        print(text, end="")
    else:
        args.out.write_text(text)
        print(f"written {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
