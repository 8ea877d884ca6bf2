"""register_many's throughput on the ModelNet10 noisy + partial test pairs: 1 and 2 local worker
processes and the local Ray backend, and whether they give the same records.

    python benchmarks/register_many_throughput.py                 # the 908 pairs (long: 4 runs of 908 pairs)
    python benchmarks/register_many_throughput.py --pairs 40      # a quick check
    python benchmarks/register_many_throughput.py --no-ray        # without the ray extra

Pairs: :func:`common.modelnet10_test_pairs` with protocol ``partial`` (noisy + partial, the
paper's headline; the first ``--pairs`` of the 908), passed to
:func:`logdesc_rt.register_many` as arrays (each cloud sent to a worker once), default
options (``estimator="auto"``, no ICP, seed 0).

Runs, each a fresh pool (worker start-up and model loads are part of its wall time):

- ``local 1 x 1``: one worker process, 1 onnxruntime thread;
- ``local 2 x 1``: two worker processes, 1 thread each (one per core on a 2-core machine);
- ``ray 2 x 1``: the Ray backend on a local instance (``ray.init(num_cpus=cores)``, started
  before the run and timed apart), two actors with 1 thread each;
- ``local 1 x cores``: one worker using every core (the default thread count for one worker).

Throughput is pairs / wall time of the ``register_many`` call (start-up included) and, apart,
the steady rate after every worker's first record. Records must be identical, key for key but
the timings, across the three ``x 1`` runs (equal threads per worker); the ``1 x cores`` run
sums in another order, so it is held to the same decisions (success, estimator, match count)
and poses within 1e-6 (round-off of the summation order; the largest difference is reported). The ground-truth
success rate (rotation error < 5 degrees and
translation error < 5 % of the radius) is reported per run.

Writes ``<out>/register_many_throughput.{md,json}``. Wall times depend on the machine's load:
the numbers of a shared machine are indicative only; the file records the machine.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from common import (  # noqa: E402
    RESULTS,
    SUCCESS_ROTATION_DEG,
    SUCCESS_TRANSLATION_FRACTION,
    command_line,
    machine_info,
    modelnet10_test_pairs,
    write_report,
)

from logdesc_rt.batch import available_cores, comparable, register_many  # noqa: E402
from logdesc_rt.metrics import rotation_error_deg  # noqa: E402

PROTOCOL = "partial"
TOTAL_PAIRS = 908
POSE_TOLERANCE = 1e-6  # 1 x cores sums in another order: float round-off only


def run(label: str, jobs, truth, *, backend: str, workers: int, threads: int) -> dict:
    """One register_many call: its records, wall time, steady rate and ground-truth success."""
    stamps: list[float] = []
    start = time.perf_counter()
    records = register_many(jobs, workers=workers, threads_per_worker=threads, backend=backend, seed=0,
                            progress=False, on_record=lambda record: stamps.append(time.perf_counter()))
    wall = time.perf_counter() - start
    steady = None
    if len(stamps) > workers:  # after every worker's first record: start-up excluded
        steady = (len(stamps) - workers) / (stamps[-1] - stamps[workers - 1])
    right = 0
    for record, (pose, scale) in zip(records, truth):
        if not record.get("ok"):
            continue
        estimate = np.asarray(record["transformation"])
        rotation = float(rotation_error_deg(estimate[:3, :3], pose[:3, :3]))
        shift = float(np.linalg.norm(estimate[:3, 3] - pose[:3, 3]))
        right += rotation < SUCCESS_ROTATION_DEG and shift < SUCCESS_TRANSLATION_FRACTION * scale
    summary = {
        "label": label,
        "backend": backend,
        "workers": workers,
        "threads_per_worker": threads,
        "pairs": len(records),
        "wall_s": wall,
        "pairs_per_s": len(records) / wall,
        "steady_pairs_per_s": steady,
        "first_record_s": stamps[0] - start if stamps else None,
        "errors": sum(not record.get("ok") for record in records),
        "flagged_success": sum(bool(record.get("success")) for record in records),
        "right": right,
    }
    print(f"{label}: {summary['pairs_per_s']:.2f} pairs/s ({wall:.1f} s, steady {_number(steady)} pairs/s), "
          f"{right}/{len(records)} right", flush=True)
    return {"summary": summary, "records": records}


def _number(value: float | None, digits: int = 2) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def same_decisions(first: list[dict], second: list[dict]) -> tuple[bool, float]:
    """Same success / estimator / match count for every pair, and the largest pose difference."""
    decisions = all(
        (a.get("ok"), a.get("success"), a.get("pose_estimator"), a.get("correspondence_count"))
        == (b.get("ok"), b.get("success"), b.get("pose_estimator"), b.get("correspondence_count"))
        for a, b in zip(first, second)
    )
    difference = max(
        (float(np.abs(np.asarray(a["transformation"]) - np.asarray(b["transformation"])).max())
         for a, b in zip(first, second) if a.get("ok") and b.get("ok")),
        default=0.0,
    )
    return decisions, difference


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=TOTAL_PAIRS, help=f"first N of the {TOTAL_PAIRS} pairs")
    parser.add_argument("--no-ray", action="store_true", help="skip the Ray backend")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.pairs < 1:
        parser.error("--pairs must be >= 1")

    pairs = list(modelnet10_test_pairs([PROTOCOL], count=args.pairs))
    jobs = [(f"{PROTOCOL}-{pair.index:04d}", pair.source, pair.target) for pair in pairs]
    truth = [(pair.T_gt, pair.scale) for pair in pairs]
    cores = available_cores()
    print(f"{len(jobs)} ModelNet10 {PROTOCOL} test pairs, {cores} cores", flush=True)

    runs = {}
    runs["local 1 x 1"] = run("local 1 x 1", jobs, truth, backend="local", workers=1, threads=1)
    runs["local 2 x 1"] = run("local 2 x 1", jobs, truth, backend="local", workers=2, threads=1)
    ray_start_s = None
    if not args.no_ray:
        import ray

        tick = time.perf_counter()
        ray.init(num_cpus=cores, include_dashboard=False, log_to_driver=False)
        ray_start_s = time.perf_counter() - tick
        try:
            runs["ray 2 x 1"] = run("ray 2 x 1", jobs, truth, backend="ray", workers=2, threads=1)
        finally:
            ray.shutdown()
    runs[f"local 1 x {cores}"] = run(f"local 1 x {cores}", jobs, truth, backend="local", workers=1, threads=cores)

    reference = [comparable(record) for record in runs["local 1 x 1"]["records"]]
    identical = {
        label: [comparable(record) for record in result["records"]] == reference
        for label, result in runs.items() if label.endswith("x 1")
    }
    decisions, pose_difference = same_decisions(runs["local 1 x 1"]["records"], runs[f"local 1 x {cores}"]["records"])
    consistent = all(identical.values()) and decisions and pose_difference <= POSE_TOLERANCE

    lines = [
        "# register_many throughput, ModelNet10 noisy + partial test pairs",
        "",
        f"Command: `{command_line()}`. {len(jobs)} pairs (of {TOTAL_PAIRS}), arrays in memory, default options "
        f"(estimator auto, no ICP, seed 0); {cores} cores. Wall time includes starting the workers and loading the "
        "model in each; steady = after every worker's first record.",
        "",
        "| run | workers x threads | pairs/s | steady pairs/s | wall s | first record s | errors | flagged success "
        "| right (< 5 deg, < 5 %) |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for label, result in runs.items():
        s = result["summary"]
        lines.append(
            f"| {label} | {s['workers']} x {s['threads_per_worker']} | {s['pairs_per_s']:.2f} | "
            f"{_number(s['steady_pairs_per_s'])} | {s['wall_s']:.1f} | {_number(s['first_record_s'], 1)} | "
            f"{s['errors']} | "
            f"{s['flagged_success']} | {s['right']} ({100.0 * s['right'] / s['pairs']:.1f} %) |"
        )
    lines += [
        "",
        "Same results: " + ", ".join(f"{label} {'identical' if same else 'DIFFERENT'}"
                                     for label, same in identical.items())
        + f" (every key but timings, against local 1 x 1); local 1 x {cores}: "
        + ("same decisions" if decisions else "DIFFERENT decisions")
        + f", largest pose difference {pose_difference:.1e} (tolerance {POSE_TOLERANCE:g}).",
    ]
    if ray_start_s is not None:
        lines.append(f"Ray's local instance took {ray_start_s:.1f} s to start (not in the ray row's wall time).")
    lines += ["", "Measured on a machine other jobs may share: the rates are indicative; `machine` in the JSON "
              "file says which machine."]
    markdown = "\n".join(lines) + "\n"
    payload = {
        "command": command_line(),
        "machine": machine_info(),
        "protocol": PROTOCOL,
        "pairs": len(jobs),
        "runs": {label: result["summary"] for label, result in runs.items()},
        "identical_records": identical,
        "all_cores_same_decisions": decisions,
        "all_cores_max_pose_difference": pose_difference,
        "ray_start_s": ray_start_s,
        "consistent": consistent,
    }
    md_path, json_path = write_report("register_many_throughput", markdown, payload, args.out)
    print(markdown)
    print(f"wrote {md_path}, {json_path}")
    return 0 if consistent else 1


if __name__ == "__main__":
    raise SystemExit(main())
