"""The runtime's stage times against an earlier commit, interleaved, on the same pair.

    python benchmarks/runtime_ab.py --baseline REV [--rounds 4] [--calls 7] [--size 1024]
        [--threads 2] [--stem runtime_ab]

This machine's speed drifts by a third within minutes, so two benchmark runs made minutes
apart do not compare. Here the baseline (a git worktree of REV, made in a temporary folder)
and the working tree alternate: ``--rounds`` rounds, each one fresh process per side, each
process one warm-up ``register`` and ``--calls`` timed ones on the pair of
``benchmarks/latency.py`` (the Bunny scan bun000 at N points, its fixed motion, noise and
permutation; seeded FSR / RANSAC). A cell is the median over rounds of each process's median
stage time (``RegistrationResult.timings``); ratio = baseline / current (> 1: faster now), from
the same rounds. Both sides run the model bundled in their own tree, with their own code.

Writes ``benchmarks/results/<stem>.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import numpy as np  # noqa: E402
from common import command_line, machine_info, write_report  # noqa: E402

STAGES = ("geometry", "descriptors", "matcher", "matching", "pose", "verification", "total")
NETWORK_STAGES = ("descriptors", "matcher")

# One side's process: import the package of TREE, time register on latency.py's pair.
_CHILD = r"""
import json, sys
tree, size, calls, threads = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
sys.path[:0] = [tree, tree + "/benchmarks"]
import numpy as np
import logdesc_rt
assert logdesc_rt.__file__.startswith(tree), logdesc_rt.__file__
from latency import POSE_SEED, bunny_pairs
pair = bunny_pairs([size], 1234)[0][size]
from logdesc_rt import Registrar
registrar = Registrar(threads=threads, max_points=size)
registrar.register(pair["source"], pair["target"], seed=POSE_SEED)
timings = [registrar.register(pair["source"], pair["target"], seed=POSE_SEED).timings for _ in range(calls)]
print(json.dumps({stage: float(np.median([t[stage] for t in timings])) for stage in timings[0]}))
"""


def run_side(tree: Path, args) -> dict[str, float]:
    command = [sys.executable, "-c", _CHILD, str(tree), str(args.size), str(args.calls), str(args.threads)]
    output = subprocess.run(command, capture_output=True, text=True, check=True, cwd=tree).stdout
    return json.loads(output.strip().splitlines()[-1])


def with_non_network(times: dict[str, float]) -> dict[str, float]:
    return {**times, "non-network": times["total"] - sum(times[stage] for stage in NETWORK_STAGES)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--baseline", required=True, help="git revision to compare with")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--calls", type=int, default=7)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--stem", default="runtime_ab")
    args = parser.parse_args(argv)
    revision = subprocess.run(["git", "rev-parse", "--short", args.baseline], capture_output=True, text=True,
                              check=True, cwd=ROOT).stdout.strip()
    current = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             check=True, cwd=ROOT).stdout.strip()
    with tempfile.TemporaryDirectory() as folder:
        baseline_tree = Path(folder) / "baseline"
        subprocess.run(["git", "worktree", "add", "--detach", str(baseline_tree), revision], check=True,
                       cwd=ROOT, capture_output=True)
        # The baseline's benchmarks find the shared data beside their tree.
        (Path(folder) / "shared").symlink_to(ROOT.parent / "shared")
        try:
            rounds = []
            for round_index in range(args.rounds):
                baseline = with_non_network(run_side(baseline_tree, args))
                now = with_non_network(run_side(ROOT, args))
                rounds.append({"baseline": baseline, "current": now})
                print(f"round {round_index + 1}: total {1e3 * baseline['total']:.0f} -> {1e3 * now['total']:.0f} ms, "
                      f"non-network {1e3 * baseline['non-network']:.0f} -> {1e3 * now['non-network']:.0f} ms", flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(baseline_tree)], cwd=ROOT, capture_output=True)

    stages = (*STAGES[:-1], "non-network", "total")
    lines = [
        "# Runtime stage times against an earlier commit, interleaved",
        "",
        f"`{command_line()}`: baseline {revision} against the working tree at {current} (plus any uncommitted "
        f"change), {args.rounds} alternating rounds of one fresh process per side, {args.calls} timed `register` "
        f"calls each after a warm-up, N = {args.size}, {args.threads} threads; the pair of `benchmarks/latency.py`. "
        "Cells: median over rounds of each process's median, ms; ratio = baseline / current (> 1: faster now). "
        "non-network = total - descriptor net - matcher net. Machine: "
        + ", ".join(f"{key} {value}" for key, value in machine_info().items()) + ".",
        "",
        "| stage | baseline ms | current ms | ratio |",
        "| --- | ---: | ---: | ---: |",
    ]
    summary = {}
    for stage in stages:
        before = float(np.median([r["baseline"][stage] for r in rounds])) * 1e3
        after = float(np.median([r["current"][stage] for r in rounds])) * 1e3
        summary[stage] = {"baseline_ms": before, "current_ms": after, "ratio": before / after}
        lines.append(f"| {stage} | {before:.1f} | {after:.1f} | {before / after:.2f}x |")
    write_report(args.stem, "\n".join(lines), {"command": command_line(), "baseline": revision, "current": current,
                                               "rounds": rounds, "summary": summary, "machine": machine_info()})
    print("\n".join(lines[-len(stages) - 2:]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
