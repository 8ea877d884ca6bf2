"""CPU latency of logdesc-rt against cloud size, beside torch eager and Open3D.

    python benchmarks/latency.py [--sizes 512 1024 2048 4096] [--repeats 5] [--rounds 1]
        [--threads 2] [--no-torch] [--no-open3d] [--out benchmarks/results]

Writes ``latency.md``, ``latency.json`` and ``latency_vs_points.png`` into ``--out``.

Clouds: real data at every N. The Stanford Bunny scan ``bun000.ply`` (40,256 points)
is farthest-point sampled to N points, centred, scaled into the unit sphere and turned
by -90 degrees about x (``WORKING_TURN``: see the comment there): the source. The target
is the source moved by one fixed, seeded rigid motion (drawn as
:mod:`logdesc_rt.synthetic` draws it: Euler angles uniform in [0, 45] degrees per axis,
translation uniform in [-0.5, 0.5] per axis; the same motion at every N). Each cloud
then gets its own Gaussian noise (sigma 0.01, clipped at 0.05, the "noisy" protocol)
and its own random permutation. Every method and backend sees the very same pairs.

Threads: T = ``--threads`` (default 2, the cores of the project's CI-class machine) is
onnxruntime's intra-op thread count (``Registrar(threads=T)``), torch's
(``torch.set_num_threads(T)``), and OMP / OpenBLAS / MKL's in every child process, so
Open3D's OpenMP code (FPFH, RANSAC) and pykdtree run on T threads too.

Processes: every measurement runs in a fresh child (this script re-invoked with a
hidden ``--worker`` flag; it prints its result as JSON on stdout). Its memory peak is
then its own, and no thread pool or allocator cache carries over between measurements.

What every number means. Times are milliseconds, "median / p90" over ``--repeats``
calls; each child makes one untimed warm-up call first.

1. Stages (onnxruntime): ``Registrar(threads=T).register(source, target)`` at the model's
   working size (clouds larger than it are subsampled, as for any user). From its ``timings``:
   geometry = ``compute_geometry`` of both clouds (NumPy/SciPy/pykdtree);
   descriptor net = the descriptor ONNX graph on both clouds; matcher net = the
   matcher graph (normal-encoder transformer + scores) on the pair; Sinkhorn + mutual
   = log-Sinkhorn with the learned dustbin, then mutual matches; pose = the candidate
   poses and the returned pose's re-fit; verification = scoring them on the clouds; other =
   load/validation + subsampling + the fitness evaluation; end to end
   = ``timings["total"]``, the sum of all of them; wall = the ``register`` call timed
   from outside (adds the pair normalisation and building the result). The mutual
   match count and the rotation error (degrees, against the true motion) of the last
   call say what the timed calls achieved.
2. onnxruntime (ORT) vs torch eager: the same weights (the shipped ONNX model was
   exported from the checkpoint its manifest names), the same float32 inputs
   (the geometry is computed once, by the parent), the same T threads, torch under
   ``torch.inference_mode()``. Each backend calls its two networks directly (no
   pipeline around them) in its own child: descriptor net = both clouds, matcher net
   = the pair, both = their sum per call. ratio = torch median / ORT median (> 1: ORT
   is faster). max abs diff = the largest absolute difference between the backends'
   descriptors, and between their scores, on those inputs: both run the same network
   up to float32 rounding.
3. Peak memory (MiB): the child's peak resident set, ``VmHWM`` of /proc/self/status
   (:func:`peak_rss_kib` says why not ``ru_maxrss``). Baselines, one per backend: a
   child that imports the backend and loads the model, then runs nothing. ORT
   register = warm-up + timed ``register`` calls at N (geometry, Sinkhorn and pose
   included); ORT network and torch network = the bare networks at N, as in 2 (the
   torch child's peak is taken before it loads onnxruntime for max abs diff). above
   baseline = peak - that backend's baseline: what the work at N costs.
4. Peers: ``benchmarks/methods.MethodRunner(("fpfh_ransac", "fpfh_fgr", "kiss_matcher"))``
   with the parameters tuned on validation pairs (``FpfhParameters.tuned()``; KISS-Matcher's
   voxel is the tuned Open3D voxel); each time
   includes the normals and FPFH of both clouds, as in the accuracy benchmark. ratio =
   its median / logdesc-rt's median wall end to end (> 1: logdesc-rt is faster).
   Open3D's RANSAC and FPFH are multithreaded (OpenMP), on the same T threads.
5. Start-up, once per process and in none of the figures above: building the
   ``Registrar`` (reading and checking the model, creating both onnxruntime sessions),
   its first ``register`` call (the warm-up), and torch's ``load_model``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from common import (  # noqa: E402
    DATA_ROOT,
    DEFAULT_SEED,
    RESULTS,
    ROOT,
    command_line,
    machine_info,
    write_report,
)
from scipy.spatial.transform import Rotation  # noqa: E402

from logdesc_rt.io import read_point_cloud  # noqa: E402
from logdesc_rt.network import bundled_model_dir, read_manifest  # noqa: E402
from logdesc_rt.sampling import farthest_point_sampling  # noqa: E402
from logdesc_rt.synthetic import (  # noqa: E402
    MAX_ANGLE_DEG,
    MAX_TRANSLATION,
    NOISE_CLIP,
    NOISE_SIGMA,
)

STEM = "latency"
DEFAULT_SIZES = (512, 1024, 2048, 4096)
BUNNY_SCAN = DATA_ROOT / "stanford_bunny" / "data" / "bun000.ply"
OPEN3D_PEERS = ("fpfh_ransac", "fpfh_fgr", "kiss_matcher")
# Pinned to --threads in every child, so that every library uses the same T threads.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
RESULT_MARKER = "LATENCY_RESULT "  # starts the child's one line of JSON on stdout
POSE_SEED = 0  # FSR / RANSAC seed: every repeat does the same work
# Latency is measured on registrations that succeed, so that Sinkhorn / FSR do the work of a
# real success. The first shipped model (v1, trained on upright pairs only) failed on this pair
# in the scan's own frame (about 100 deg) and registered it turned by -90 degrees about x.
# Later models do not depend on orientation; the turn stays so that the recorded timings of
# every model are on the same clouds.
WORKING_TURN = Rotation.from_euler("x", -90.0, degrees=True).as_matrix()

# (key of a stage summary, column title): RegistrationResult.timings keys, plus
# "other" (the OTHER_STAGES summed) and "wall" (the call timed from outside).
STAGE_COLUMNS = (
    ("geometry", "geometry"),
    ("descriptors", "descriptor net"),
    ("matcher", "matcher net"),
    ("matching", "Sinkhorn + mutual (float32)"),
    ("pose", "pose (candidates, re-fit)"),
    ("verification", "verification"),
    ("other", "other"),
    ("total", "end to end"),
    ("wall", "wall"),
)
OTHER_STAGES = ("load", "subsample", "evaluation")
NETWORK_PARTS = ("descriptors", "matcher", "both")


# ------------------------------------------------------------------------ helpers
def network_flops(config: dict, source_points: int, target_points: int, neighbours: int) -> float:
    """Floating-point operations (2 per multiply-add) of the invariant network on one pair.

    Counted from the model config (``manifest.json`` "model_config"): the edge convolutions
    (per point and neighbour), the geometric self-attention layers of the descriptor and of the
    matcher (Q, K, V and merge projections, the update MLP, Q K^T over head channels plus the
    26 geometric channels per head, and the weighted sum of V), the bidirectional cross layers
    (both directions), the final projections and the N x M score product. Norms, softmax and
    activations are left out (a few per cent).
    """
    geometric_channels = 5 + 6 + 15  # distance, (n.n)^2 and (n.n)^4 channels per head

    def multiply_adds_self(width: int, heads: int, count: int) -> float:
        per_point = 4 * width * width + (2 * width) * (2 * width) + (2 * width) * width + width * 2 * heads
        logits = count * count * (width + heads * geometric_channels)
        return count * per_point + logits + count * count * width

    def multiply_adds_cross(width: int, first: int, second: int) -> float:
        projections = (first + second) * (2 * width * width + width * width)
        updates = (first + second) * ((2 * width) * (2 * width) + (2 * width) * width)
        return projections + updates + 2 * (2 * first * second * width)

    channels = [config["edge_channels"], *config["descriptor_channels"]]
    edge = neighbours * sum(a * b for a, b in zip(channels[:-1], channels[1:]))
    width, dim = config["descriptor_channels"][-1], config["descriptor_dim"]
    total = 0.0
    for count in (source_points, target_points):
        total += count * edge + count * width * dim
        total += config["descriptor_attention_layers"] * multiply_adds_self(width, config["descriptor_heads"], count)
        total += config["transformer_layers"] * multiply_adds_self(dim, config["transformer_heads"], count)
        total += count * dim * dim  # the matcher's final projection
    total += config["transformer_layers"] * multiply_adds_cross(dim, source_points, target_points)
    total += source_points * target_points * dim  # the scores
    return 2.0 * total


def summary_ms(seconds: list[float]) -> dict:
    """Median and 90th percentile (ms) of timings given in seconds."""
    values = 1e3 * np.asarray(seconds, dtype=np.float64)
    return {
        "median_ms": float(np.median(values)),
        "p90_ms": float(np.percentile(values, 90)),
        "samples": len(values),
    }


def time_calls(function: Callable[[], object], repeats: int) -> list[float]:
    """Wall seconds of ``repeats`` calls of ``function``, after one untimed warm-up."""
    function()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        samples.append(time.perf_counter() - start)
    return samples


def peak_rss_kib() -> dict[str, int]:
    """Peak resident memory of this process, KiB: ``vmhwm_kib`` and ``ru_maxrss_kib``.

    Why VmHWM and not ``ru_maxrss``: on Linux, ``ru_maxrss`` survives fork + exec (the
    kernel folds the forked copy's high-water mark into the child's), so a child of a
    parent that holds 400 MB reports ``ru_maxrss`` >= 400 MB without ever touching them
    (seen on the project machine: 408 MiB against a VmHWM of 11 MiB). VmHWM is the peak
    of the child's own address space. ``ru_maxrss`` is kept for reference and stands in
    for VmHWM where there is no /proc (not Linux).
    """
    import resource

    maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    if sys.platform == "darwin":  # bytes there, KiB on Linux
        maxrss //= 1024
    peak = {"ru_maxrss_kib": int(maxrss), "vmhwm_kib": int(maxrss)}
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    peak["vmhwm_kib"] = int(line.split()[1])
    except OSError:
        pass
    return peak


def format_ms(value: float) -> str:
    """Milliseconds to about three significant digits."""
    if not math.isfinite(value):
        return ""
    if value < 10:
        return f"{value:.2f}"
    if value < 100:
        return f"{value:.1f}"
    return f"{value:.0f}"


def cell(summary: dict | None) -> str:
    """'median / p90' of a :func:`summary_ms` result ('' if there is none)."""
    if not summary:
        return ""
    return f"{format_ms(summary['median_ms'])} / {format_ms(summary['p90_ms'])}"


def ratio(numerator: dict | None, denominator: dict | None) -> float:
    """Median of one summary over the median of another (NaN if either is missing)."""
    if not numerator or not denominator:
        return float("nan")
    return numerator["median_ms"] / denominator["median_ms"]


def format_ratio(value: float) -> str:
    return f"{value:.2f}x" if math.isfinite(value) else ""


def mib(kib: float) -> float:
    return kib / 1024.0


# ------------------------------------------------------------------------ the pairs
def bunny_pairs(sizes: list[int], seed: int) -> tuple[dict[int, dict], int]:
    """The registration pair of every size, and the scan's point count.

    Returns:
        N -> {"source": (N, 3), "target": (N, 3) float64 clouds in the unit sphere,
        "T_gt": (4, 4) true pose source -> target}; the number of points in the scan.
    """
    scan = read_point_cloud(BUNNY_SCAN)
    largest = max(sizes)
    if largest > len(scan):
        raise ValueError(
            f"--sizes: {largest} > the {len(scan)} points of {BUNNY_SCAN.name}"
        )
    # Farthest-point sampling is greedy: its first N picks are the N-point sample, so
    # one run for the largest N serves every size.
    order = farthest_point_sampling(scan, largest)

    # One motion for every N, so that the sizes differ only in their points.
    motion_rng = np.random.default_rng([seed, 0])
    angles_xyz = motion_rng.uniform(0.0, math.radians(MAX_ANGLE_DEG), size=3)
    rotation = Rotation.from_euler("zyx", angles_xyz[::-1]).as_matrix()
    translation = motion_rng.uniform(-MAX_TRANSLATION, MAX_TRANSLATION, size=3)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, translation

    pairs = {}
    for size in sizes:
        rng = np.random.default_rng([seed, size])
        points = scan[order[:size]]
        points = points - points.mean(axis=0)
        points = points / np.linalg.norm(points, axis=1).max()
        points = points @ WORKING_TURN.T
        moved = points @ rotation.T + translation
        source = _with_noise(points, rng)[rng.permutation(size)]
        target = _with_noise(moved, rng)[rng.permutation(size)]
        pairs[size] = {"source": source, "target": target, "T_gt": pose}
    return pairs, len(scan)


REAL_PAIR = "bun000-bun045"  # the key of the real scan pair among the sizes
REAL_PAIR_POINTS = 2048


def real_scan_pair(points: int = REAL_PAIR_POINTS) -> dict:
    """The real Stanford Bunny scans bun000 -> bun045 as a user has them (metres, each in its
    scanner's frame), each farthest-point sampled to ``points``; truth from ``bun.conf``."""
    from bunny import fps_subset, load_scans, relative_pose

    scans = {scan.name: scan for scan in load_scans()}
    source, target = scans["bun000.ply"], scans["bun045.ply"]
    return {
        "source": fps_subset(source.points, points),
        "target": fps_subset(target.points, points),
        "T_gt": relative_pose(source, target),
    }


def _with_noise(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) points + N(0, sigma^2) per coordinate, clipped as the "noisy" protocol."""
    noise = rng.normal(0.0, NOISE_SIGMA, size=points.shape)
    return points + np.clip(noise, -NOISE_CLIP, NOISE_CLIP)


def network_inputs(registrar, source: np.ndarray, target: np.ndarray) -> dict[str, np.ndarray]:
    """The networks' inputs for one pair: ``registrar.prepare``, whose working size must be at
    least N (so that nothing is subsampled; both backends see the same points: the stray-point
    test may set a few aside, at most 1 %).

    Returns:
        float32 arrays: src_edges / tgt_edges (N, k, 15); src_points / tgt_points
        (N, 3), network units; src_normals / tgt_normals (N, 3) unit normals.
    """
    prepared = registrar.prepare(source, target)
    if len(prepared.source_index) < 0.99 * len(source) or len(prepared.target_index) < 0.99 * len(target):
        raise ValueError(f"the registrar's working size {registrar.max_points} would subsample the pair")
    inputs = {}
    for prefix, points, geometry in (
        ("src", prepared.source_network, prepared.source_geometry),
        ("tgt", prepared.target_network, prepared.target_geometry),
    ):
        inputs[f"{prefix}_edges"] = geometry.edges.astype(np.float32)
        inputs[f"{prefix}_points"] = points.astype(np.float32)
        inputs[f"{prefix}_normals"] = geometry.normals.astype(np.float32)
    return inputs


def save_inputs(path: Path, pairs: dict[int, dict], model_dir: Path | None = None) -> None:
    """Write every pair and its network inputs into the one .npz all children read."""
    from logdesc_rt import Registrar  # as in the children: the parent stays light until needed

    # One registrar (one model load) for every size: its working size is the largest N.
    largest = max(len(pair[name]) for pair in pairs.values() for name in ("source", "target"))
    registrar = Registrar(model_dir, max_points=largest)
    arrays = {}
    for size, pair in pairs.items():
        arrays.update({f"{name}_{size}": value for name, value in pair.items()})
        inputs = network_inputs(registrar, pair["source"], pair["target"])
        arrays.update({f"{name}_{size}": value for name, value in inputs.items()})
    np.savez(path, **arrays)


def load_inputs(path: Path, size: int) -> dict[str, np.ndarray]:
    """The arrays of one size from :func:`save_inputs`'s file (names without _N)."""
    suffix = f"_{size}"
    with np.load(path) as archive:
        return {
            key[: -len(suffix)]: archive[key]
            for key in archive.files
            if key.endswith(suffix)
        }


# ------------------------------------------------------------------------ children
def worker_baseline_onnxruntime(args) -> dict:
    """Import the runtime and load the model (both sessions); run nothing."""
    from logdesc_rt import Registrar

    Registrar(args.model_dir, threads=args.threads)
    return {"peak": peak_rss_kib()}


def worker_onnxruntime(args) -> dict:
    """``register`` at N: stage timings, wall time, start-up, peak memory."""
    from logdesc_rt import Registrar
    from logdesc_rt.metrics import rotation_error_deg

    data = load_inputs(args.inputs, args.size)
    start = time.perf_counter()
    registrar = Registrar(args.model_dir, threads=args.threads)  # the model's own working size
    startup = time.perf_counter() - start

    start = time.perf_counter()  # the warm-up call, timed as the first call
    result = registrar.register(data["source"], data["target"], seed=POSE_SEED)
    first_call = time.perf_counter() - start

    stages: dict[str, list[float]] = {}
    for _ in range(args.repeats):
        start = time.perf_counter()
        result = registrar.register(data["source"], data["target"], seed=POSE_SEED)
        stages.setdefault("wall", []).append(time.perf_counter() - start)
        for stage, seconds in result.timings.items():
            stages.setdefault(stage, []).append(seconds)
    other = zip(*(stages[stage] for stage in OTHER_STAGES), strict=True)
    stages["other"] = [sum(calls) for calls in other]
    pose, truth = result.transformation, data["T_gt"]
    config = registrar.network.manifest.model_config
    k = registrar.network.manifest.geometry.umbrella_neighbours
    flops = network_flops(config, result.source_points_used, result.target_points_used, k)
    network_seconds = np.median(np.add(stages["descriptors"], stages["matcher"]))
    return {
        "working_size": registrar.max_points,
        "points_used": [result.source_points_used, result.target_points_used],
        "network_gflop": flops / 1e9,
        "network_gflop_per_s": flops / 1e9 / network_seconds,
        "success": bool(result.success),
        "stages_s": stages,
        "stages": {stage: summary_ms(values) for stage, values in stages.items()},
        "matches": len(result.correspondences),
        "rotation_error_deg": float(rotation_error_deg(pose[:3, :3], truth[:3, :3])),
        "translation_error": float(np.linalg.norm(pose[:3, 3] - truth[:3, 3])),
        "startup_s": startup,
        "first_call_s": first_call,
        "peak": peak_rss_kib(),
    }


def _time_networks(describe: Callable, match: Callable, data: dict, repeats: int):
    """Time ``describe`` on both clouds and ``match`` on the pair, per call.

    Args:
        describe: (edges, points, normals) -> descriptors, in the backend's array type.
        match: (desc_src, desc_tgt, normals_src, normals_tgt, points_src, points_tgt) -> scores
            (each network reads the inputs its architecture uses).
        data: the backend's arrays, keyed as :func:`network_inputs` keys them.

    Returns:
        ({"descriptors": seconds, "matcher": seconds, "both": their per-call sums},
        {"src": descriptors, "tgt": descriptors, "scores": scores} of the last call).
    """
    outputs = {}

    def describe_both() -> None:
        for prefix in ("src", "tgt"):
            outputs[prefix] = describe(
                data[f"{prefix}_edges"], data[f"{prefix}_points"], data[f"{prefix}_normals"]
            )

    def match_pair() -> None:
        outputs["scores"] = match(
            outputs["src"], outputs["tgt"], data["src_normals"], data["tgt_normals"],
            data["src_points"], data["tgt_points"],
        )

    seconds = {
        "descriptors": time_calls(describe_both, repeats),
        "matcher": time_calls(match_pair, repeats),
    }
    seconds["both"] = [
        a + b for a, b in zip(seconds["descriptors"], seconds["matcher"], strict=True)
    ]
    return seconds, outputs


def worker_onnxruntime_network(args) -> dict:
    """The two ONNX graphs alone at N (``OnnxNetwork``): timings and peak memory."""
    from logdesc_rt.network import OnnxNetwork

    data = load_inputs(args.inputs, args.size)
    network = OnnxNetwork(args.model_dir, threads=args.threads)  # as Registrar(threads=T) builds it
    seconds, _ = _time_networks(
        network.describe, network.match_scores, data, args.repeats
    )
    return {
        "network_s": seconds,
        "network": {part: summary_ms(values) for part, values in seconds.items()},
        "peak": peak_rss_kib(),
    }


def _load_torch_model(args):
    """(torch, the model in eval mode), on T threads; ImportError without torch."""
    import torch

    torch.set_num_threads(args.threads)
    from training.checkpoint import load_model

    model, _ = load_model(args.checkpoint)
    return torch, model


def worker_baseline_torch(args) -> dict:
    """Import torch and load the checkpoint; run nothing."""
    try:
        _load_torch_model(args)
    except ImportError as error:
        return {"available": False, "reason": f"import failed: {error}"}
    return {"available": True, "peak": peak_rss_kib()}


def worker_torch(args) -> dict:
    """The two networks in torch eager at N; then ORT once, for max abs diff."""
    try:
        start = time.perf_counter()
        torch, model = _load_torch_model(args)
        load_seconds = time.perf_counter() - start
    except ImportError as error:
        return {"available": False, "reason": f"import failed: {error}"}
    data = load_inputs(args.inputs, args.size)
    # The model takes a batch dimension first: (1, N, k, 15), (1, N, 3).
    tensors = {
        name: torch.from_numpy(value[None])
        for name, value in data.items()
        if name.startswith(("src_", "tgt_"))
    }
    with torch.inference_mode():
        seconds, outputs = _time_networks(
            model.describe, model.match_scores, tensors, args.repeats
        )
    peak = peak_rss_kib()  # before onnxruntime is loaded below

    difference = {}
    try:
        from logdesc_rt.network import OnnxNetwork

        network = OnnxNetwork(args.model_dir, threads=args.threads)
        # repeats=0: just the one (warm-up) call, for its outputs.
        _, reference = _time_networks(network.describe, network.match_scores, data, 0)
        gaps = {
            name: np.abs(outputs[name][0].numpy() - reference[name]).max()
            for name in reference
        }
        difference = {
            "descriptors": float(max(gaps["src"], gaps["tgt"])),
            "scores": float(gaps["scores"]),
        }
    except ImportError:
        pass
    return {
        "available": True,
        "torch": torch.__version__,
        "load_model_s": load_seconds,
        "network_s": seconds,
        "network": {part: summary_ms(values) for part, values in seconds.items()},
        "max_abs_difference": difference,
        "peak": peak,
    }


def worker_open3d(args) -> dict:
    """FPFH + RANSAC and FPFH + FGR (Open3D) on the pair of size N."""
    try:
        import open3d
    except ImportError as error:
        return {"available": False, "reason": f"import failed: {error}"}
    from methods import FpfhParameters, MethodRunner, parameters_dict

    from logdesc_rt.metrics import rotation_error_deg

    data = load_inputs(args.inputs, args.size)
    parameters = FpfhParameters.tuned()
    try:
        import kiss_matcher  # noqa: F401 (the bench extra)

        peers = OPEN3D_PEERS
    except ImportError:
        peers = tuple(name for name in OPEN3D_PEERS if name != "kiss_matcher")
    runner = MethodRunner(peers, parameters=parameters)
    runner.run(data["source"], data["target"], seed=POSE_SEED)  # warm-up
    seconds: dict[str, list[float]] = {name: [] for name in peers}
    for _ in range(args.repeats):
        results = runner.run(data["source"], data["target"], seed=POSE_SEED)
        for name, result in results.items():
            seconds[name].append(result.seconds)
    truth = data["T_gt"][:3, :3]
    return {
        "available": True,
        "open3d": open3d.__version__,
        "parameters": parameters_dict(parameters),
        "seconds": seconds,
        "methods": {name: summary_ms(values) for name, values in seconds.items()},
        "rotation_error_deg": {
            name: float(rotation_error_deg(result.transformation[:3, :3], truth))
            for name, result in results.items()
        },
        "peak": peak_rss_kib(),
    }


WORKERS = {
    "baseline_onnxruntime": worker_baseline_onnxruntime,
    "onnxruntime": worker_onnxruntime,
    "onnxruntime_network": worker_onnxruntime_network,
    "baseline_torch": worker_baseline_torch,
    "torch": worker_torch,
    "open3d": worker_open3d,
}


def run_child(kind: str, size: int, inputs: Path, args) -> dict:
    """One measurement in a fresh interpreter; its JSON result."""
    options = {
        "--worker": kind,
        "--size": size,
        "--inputs": inputs,
        "--threads": args.threads,
        "--repeats": args.repeats,
    }
    if args.checkpoint is not None:
        options["--checkpoint"] = args.checkpoint
    if args.model_dir is not None:
        options["--model-dir"] = Path(args.model_dir).resolve()
    command = [sys.executable, str(Path(__file__).resolve())]
    command += [str(part) for option in options.items() for part in option]
    environment = dict(
        os.environ, **{name: str(args.threads) for name in THREAD_VARIABLES}
    )
    completed = subprocess.run(
        command, capture_output=True, text=True, env=environment, cwd=ROOT
    )
    if completed.returncode != 0:
        raise RuntimeError(
            f"child {kind} at N={size} failed (exit {completed.returncode}):\n"
            f"{completed.stderr[-4000:]}"
        )
    for line in reversed(completed.stdout.splitlines()):
        if line.startswith(RESULT_MARKER):
            return json.loads(line[len(RESULT_MARKER) :])
    raise RuntimeError(
        f"child {kind} at N={size} printed no result:\n{completed.stdout}"
    )


# ------------------------------------------------------------------------ the report
def row(size: int, cells: list[str]) -> str:
    return f"| {size} | " + " | ".join(cells) + " |"


def header(titles: list[str]) -> list[str]:
    return ["| N | " + " | ".join(titles) + " |", "| ---: |" + " ---: |" * len(titles)]


def stages_table(results: dict[int, dict]) -> list[str]:
    titles = ["points used"] + [title for _, title in STAGE_COLUMNS]
    titles += ["matches", "rot. err. deg", "success", "network GFLOP", "network GFLOP/s"]
    lines = header(titles)
    for size, result in results.items():
        run = result["onnxruntime"]
        cells = [" x ".join(str(n) for n in run["points_used"])]
        cells += [cell(run["stages"].get(key)) for key, _ in STAGE_COLUMNS]
        cells += [str(run["matches"]), f"{run['rotation_error_deg']:.2f}", str(run["success"])]
        cells += [f"{run['network_gflop']:.2f}", f"{run['network_gflop_per_s']:.0f}"]
        lines.append(row(size, cells))
    return lines


def backends_table(results: dict[int, dict]) -> list[str]:
    titles = []
    for part in ("descriptor net", "matcher net", "both"):
        titles += [f"{part} ORT", "torch", "ratio"]
    lines = header(titles + ["max abs diff descriptors", "max abs diff scores"])
    for size, result in results.items():
        ort = result["onnxruntime_network"]["network"]
        eager = (result.get("torch") or {}).get("network") or {}
        cells = []
        for part in NETWORK_PARTS:
            summary = eager.get(part)
            cells += [
                cell(ort[part]),
                cell(summary),
                format_ratio(ratio(summary, ort[part])),
            ]
        difference = (result.get("torch") or {}).get("max_abs_difference") or {}
        for name in ("descriptors", "scores"):
            cells.append(f"{difference[name]:.1e}" if name in difference else "")
        lines.append(row(size, cells))
    return lines


MEMORY_COLUMNS = (
    ("onnxruntime", "onnxruntime", "ORT register"),
    ("onnxruntime_network", "onnxruntime", "ORT network"),
    ("torch", "torch", "torch network"),
)


def memory_table(results: dict[int, dict], baselines: dict[str, dict]) -> list[str]:
    titles = []
    for _, _, title in MEMORY_COLUMNS:
        titles += [f"{title} peak", "above baseline"]
    lines = header(titles)
    for size, result in results.items():
        cells = []
        for kind, backend, _ in MEMORY_COLUMNS:
            run, baseline = result.get(kind), baselines.get(backend)
            if not run or not baseline:
                cells += ["", ""]
                continue
            peak = run["peak"]["vmhwm_kib"]
            above = peak - baseline["peak"]["vmhwm_kib"]
            cells += [f"{mib(peak):.0f}", f"{mib(above):.0f}"]
        lines.append(row(size, cells))
    return lines


def open3d_table(results: dict[int, dict]) -> list[str]:
    titles = ["logdesc-rt wall", "rot. err. deg"]
    for title in ("FPFH + RANSAC", "FPFH + FGR", "KISS-Matcher"):
        titles += [title, "ratio", "rot. err. deg"]
    lines = header(titles + ["Open3D child peak MiB"])
    for size, result in results.items():
        logdesc = result["onnxruntime"]["stages"]["wall"]
        peers = result.get("open3d")
        cells = [cell(logdesc), f"{result['onnxruntime']['rotation_error_deg']:.2f}"]
        for name in OPEN3D_PEERS:
            if not peers or name not in peers["methods"]:
                cells += ["", "", ""]
                continue
            summary = peers["methods"][name]
            error = peers["rotation_error_deg"][name]
            cells += [
                cell(summary),
                format_ratio(ratio(summary, logdesc)),
                f"{error:.2f}",
            ]
        cells.append(f"{mib(peers['peak']['vmhwm_kib']):.0f}" if peers else "")
        lines.append(row(size, cells))
    return lines


def round_summary(results: dict) -> dict:
    """One round's medians: logdesc-rt's wall and each Open3D peer's, ms, per size."""
    summary = {}
    for size, result in results.items():
        if "onnxruntime" not in result:
            continue
        peers = result.get("open3d") or {"methods": {}}
        summary[str(size)] = {
            "logdesc_rt_wall_ms": result["onnxruntime"]["stages"]["wall"]["median_ms"],
            **{f"{name}_ms": peers["methods"][name]["median_ms"] for name in OPEN3D_PEERS if name in peers["methods"]},
        }
    return summary


def rounds_table(rounds: list[dict]) -> list[str]:
    """Per size, each round's logdesc-rt and FPFH + RANSAC medians and their ratio."""
    peer = OPEN3D_PEERS[0]
    lines = header([f"round {i + 1}: logdesc-rt / FPFH + RANSAC ms, ratio" for i in range(len(rounds))]
                   + ["median ratio"])
    for size in rounds[0]:
        cells, ratios = [], []
        for summary in rounds:
            ours, theirs = summary[size]["logdesc_rt_wall_ms"], summary[size].get(f"{peer}_ms")
            if theirs is None:
                cells.append(f"{format_ms(ours)} / -")
                continue
            ratios.append(theirs / ours)
            cells.append(f"{format_ms(ours)} / {format_ms(theirs)}, {format_ratio(ratios[-1])}")
        cells.append(format_ratio(float(np.median(ratios))) if ratios else "")
        lines.append(row(size, cells))
    return lines


def startup_table(results: dict[int, dict]) -> list[str]:
    lines = header(["Registrar() ms", "first register ms", "torch load_model ms"])
    for size, result in results.items():
        run, eager = result["onnxruntime"], result.get("torch")
        cells = [
            format_ms(1e3 * run["startup_s"]),
            format_ms(1e3 * run["first_call_s"]),
        ]
        cells.append(format_ms(1e3 * eager["load_model_s"]) if eager else "")
        lines.append(row(size, cells))
    return lines


def markdown_report(payload: dict) -> str:
    """The whole ``latency.md``: set-up, then one table per concern."""
    results, baselines = payload["results"], payload["baselines"]
    threads = payload["threads"]
    machine = ", ".join(f"{key} {value}" for key, value in payload["machine"].items())
    lines = [
        "# CPU latency against cloud size",
        "",
        f"Machine: {machine}. Command: `{payload['command']}`.",
        "",
        f"Model: {payload['model']} ({payload['model_architecture']} architecture), "
        f"torch checkpoint `{payload['checkpoint']}`.",
        "",
        f"Clouds: {payload['clouds']}",
        "",
        f"Threads: {threads} (onnxruntime intra-op threads, `torch.set_num_threads`, "
        f"and {', '.join(THREAD_VARIABLES)} of every child process). Every measurement "
        f"ran in a fresh process, with one warm-up call and then {payload['repeats']} "
        "timed call(s) per N. Cells are **median / p90, ms**. The docstring of "
        "`benchmarks/latency.py` defines every number.",
        "",
    ]
    if payload["skipped"]:
        lines += ["Skipped: " + " ".join(payload["skipped"]), ""]
    lines += [
        "## Stages, onnxruntime (`Registrar.register` timings)",
        "",
        "geometry and descriptor net: both clouds; other: load + subsample (a no-op "
        "here) + fitness evaluation; end to end: `timings['total']`; wall: the call "
        "timed from outside. matches and rotation error: of the last timed call.",
        "",
        *stages_table(results),
        "",
        "## onnxruntime (ORT) vs torch eager: same weights, inputs and threads",
        "",
        "Each backend calls its two networks directly on the same float32 inputs, in "
        "its own process. ratio = torch median / ORT median (> 1: ORT faster). max abs "
        "diff: between the backends' outputs (descriptors are unit vectors).",
        "",
        *backends_table(results),
        "",
        "## Peak memory, MiB (resident set high-water mark, VmHWM)",
        "",
    ]
    for backend in ("onnxruntime", "torch"):
        if baseline := baselines.get(backend):
            lines.append(
                f"- baseline {backend} (imports + model loaded, nothing run): "
                f"{mib(baseline['peak']['vmhwm_kib']):.0f} MiB"
            )
    lines += [
        "",
        "ORT register: warm-up + timed `register` calls at N (geometry, Sinkhorn, pose "
        "included); ORT / torch network: the bare networks at N. above baseline = "
        "peak - that backend's baseline.",
        "",
        *memory_table(results, baselines),
        "",
        "## Open3D peers vs logdesc-rt end to end (wall clock)",
        "",
        "Open3D's RANSAC and FPFH are multithreaded (OpenMP), here on the same "
        f"{threads} threads. Each Open3D time includes normals + FPFH of both clouds. "
        "ratio = Open3D median / logdesc-rt median (> 1: logdesc-rt faster). Rotation "
        "errors: last timed call.",
        "",
    ]
    if any(result.get("open3d") for result in results.values()):
        lines += [*open3d_table(results), ""]
    else:
        lines += ["(not measured)", ""]
    if len(payload.get("rounds", [])) > 1 and any(
        f"{OPEN3D_PEERS[0]}_ms" in sizes for summary in payload["rounds"] for sizes in summary.values()
    ):
        lines += [
            f"## Rounds ({len(payload['rounds'])}, one after the other)",
            "",
            "Every child ran once per round; the tables above are the last round's. Per round: "
            "logdesc-rt's wall median and FPFH + RANSAC's, and their ratio (> 1: logdesc-rt faster).",
            "",
            *rounds_table(payload["rounds"]),
            "",
        ]
    lines += [
        "## Start-up, once per process (in none of the tables above)",
        "",
        *startup_table(results),
        "",
        f"Figure: `{payload['stem']}_vs_points.png` (median times against N, log-log).",
    ]
    return "\n".join(lines) + "\n"


def plot_latency(results: dict[int, dict], path: Path) -> None:
    """Median time of every stage, end to end, the networks and Open3D against N."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = [size for size in results if isinstance(size, int)]
    figure, axis = plt.subplots(figsize=(10, 5.2))

    def plot(label: str, summaries: list[dict | None], **style) -> None:
        values = [s["median_ms"] if s else float("nan") for s in summaries]
        if any(math.isfinite(v) for v in values):
            axis.plot(sizes, values, label=label, **style)

    for key, title in STAGE_COLUMNS:
        if key in ("other", "wall"):
            continue
        summaries = [results[n]["onnxruntime"]["stages"][key] for n in sizes]
        if key == "total":
            plot(
                "end to end (onnxruntime)", summaries, marker="o", color="black", lw=2.5
            )
        else:
            plot(title, summaries, marker="o")
    for kind, label, style in (
        ("onnxruntime_network", "onnxruntime networks (descriptor + matcher)", "--"),
        ("torch", "torch eager networks (descriptor + matcher)", ":"),
    ):
        summaries = [
            (results[n].get(kind) or {}).get("network", {}).get("both") for n in sizes
        ]
        plot(label, summaries, marker="s", color="tab:gray", linestyle=style)
    for name, label, colour in (
        ("fpfh_ransac", "Open3D FPFH + RANSAC", "tab:blue"),
        ("fpfh_fgr", "Open3D FPFH + FGR", "tab:cyan"),
        ("kiss_matcher", "KISS-Matcher", "tab:red"),
    ):
        summaries = [
            (results[n].get("open3d") or {}).get("methods", {}).get(name) for n in sizes
        ]
        plot(label, summaries, marker="^", color=colour, linestyle="-.")

    axis.set_xscale("log", base=2)
    axis.set_yscale("log")
    axis.set_xticks(sizes, [str(n) for n in sizes])
    axis.set_xlabel("points per cloud N (log)")
    axis.set_ylabel("median time per pair, ms (log)")
    axis.set_title("CPU latency against cloud size (Stanford Bunny pairs)")
    axis.grid(True, which="both", alpha=0.3)
    axis.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0))  # outside
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=120)
    plt.close(figure)


# ------------------------------------------------------------------------ main
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes",
        type=int,
        nargs="+",
        default=list(DEFAULT_SIZES),
        help="points per cloud (default: 512 1024 2048 4096)",
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=5,
        help="timed calls per N and child (median, p90)",
    )
    parser.add_argument(
        "--threads", type=int, default=2, help="threads of every library"
    )
    parser.add_argument(
        "--seed", type=int, default=DEFAULT_SEED, help="seeds the pairs"
    )
    parser.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="torch checkpoint the ONNX model (--model-dir) was exported from (default: the one "
        "its manifest names, provenance -> checkpoint_file)",
    )
    parser.add_argument(
        "--model-dir", type=Path, default=None,
        help="model directory written by export/to_onnx.py (default: the bundled model)",
    )
    parser.add_argument("--stem", default=STEM, help="result file names: STEM.md, STEM.json, STEM_vs_points.png")
    parser.add_argument("--no-torch", action="store_true", help="skip torch eager")
    parser.add_argument("--no-real-pair", action="store_true",
                        help=f"leave out the real scan pair ({REAL_PAIR}, {REAL_PAIR_POINTS} points each)")
    parser.add_argument(
        "--no-open3d", action="store_true", help="skip the Open3D peers"
    )
    parser.add_argument(
        "--rounds", type=int, default=1,
        help="run every child this many times, one round after the other; the report's tables are "
        "the last round's, and a table gives each round's logdesc-rt / Open3D times and ratio "
        "(the machine's drift between children moves single ratios)",
    )
    parser.add_argument("--out", type=Path, default=RESULTS)
    # The child's side of the parent / child protocol (see run_child).
    parser.add_argument("--worker", choices=sorted(WORKERS), help=argparse.SUPPRESS)
    parser.add_argument("--size", help=argparse.SUPPRESS)  # N, or REAL_PAIR
    parser.add_argument("--inputs", type=Path, help=argparse.SUPPRESS)
    return parser


def child_tasks(sizes: list[int], torch: bool, open3d: bool) -> list[tuple[str, int]]:
    """(worker kind, N) of every child, in running order; baselines first."""
    tasks = [("baseline_onnxruntime", sizes[0])]
    tasks += [("baseline_torch", sizes[0])] if torch else []
    for size in sizes:
        tasks += [("onnxruntime", size), ("onnxruntime_network", size)]
        tasks += [("torch", size)] if torch else []
        tasks += [("open3d", size)] if open3d else []
    return tasks


def describe_clouds(pose: np.ndarray, scan_points: int, seed: int) -> str:
    """One paragraph on where the pairs come from, for the report."""
    angles = Rotation.from_matrix(pose[:3, :3]).as_euler("zyx", degrees=True)
    return (
        f"Stanford Bunny `../{BUNNY_SCAN.relative_to(ROOT.parent)}` ({scan_points} "
        "points), farthest-point sampled to N, centred and scaled into the unit sphere "
        "(source); target = source moved by one seeded rigid motion (seed "
        f"{seed}: Euler zyx {', '.join(f'{a:.1f}' for a in angles)} deg, translation "
        f"{', '.join(f'{t:.3f}' for t in pose[:3, 3])}), the same at every N; "
        f"independent Gaussian noise per cloud (sigma {NOISE_SIGMA}, clipped at "
        f"{NOISE_CLIP}) and independent permutations. The same pairs for every method "
        "and backend; `Registrar()` at the model's working size (larger clouds are "
        f"subsampled as `register` does). Last row: the real scans {REAL_PAIR} (metres, each in "
        f"its scanner's frame), each farthest-point sampled to {REAL_PAIR_POINTS} points, truth "
        "from bun.conf."
    )


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.worker:
        print(RESULT_MARKER + json.dumps(WORKERS[args.worker](args)))
        return 0

    from tqdm import tqdm

    model_dir = args.model_dir or bundled_model_dir()
    min_points = read_manifest(model_dir).geometry.min_points
    if args.checkpoint is None:
        exported_from = read_manifest(model_dir).provenance.get("checkpoint_file")
        if exported_from is None and not args.no_torch:
            raise SystemExit(f"{model_dir}/manifest.json names no checkpoint_file: pass --checkpoint or --no-torch")
        args.checkpoint = ROOT / exported_from if exported_from else None
    sizes = sorted(set(args.sizes))
    if sizes[0] < min_points or args.repeats < 1 or args.threads < 1:
        raise SystemExit(
            f"need --sizes >= {min_points}, --repeats >= 1, --threads >= 1"
        )
    use = {"torch": not args.no_torch, "open3d": not args.no_open3d}
    skipped = [f"{name} (--no-{name})." for name, wanted in use.items() if not wanted]

    pairs, scan_points = bunny_pairs(sizes, args.seed)
    if not args.no_real_pair:
        pairs[REAL_PAIR] = real_scan_pair()
        sizes = sizes + [REAL_PAIR]
    rounds: list[dict] = []
    baselines: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="latency_") as folder:
        inputs = Path(folder) / "inputs.npz"
        save_inputs(inputs, pairs, args.model_dir)
        tasks = child_tasks(sizes, use["torch"], use["open3d"]) * args.rounds
        results: dict = {}
        with tqdm(tasks, desc="latency", unit="child", dynamic_ncols=True) as bar:
            for kind, size in bar:
                library = (
                    "torch" if "torch" in kind else "open3d" if kind == "open3d" else ""
                )
                if library and not use[library]:
                    continue  # found unusable by an earlier child
                if kind == "baseline_onnxruntime":  # each round starts here
                    results = {size: {} for size in sizes}
                    rounds.append(results)
                bar.set_postfix_str(f"{kind} N={size} round {len(rounds)}")
                result = run_child(kind, size, inputs, args)
                if result.get("available") is False:
                    message = f"{library} is not usable ({result['reason']})."
                    tqdm.write(f"skipping {message}", file=sys.stderr)
                    skipped.append(message)
                    use[library] = False
                elif kind.startswith("baseline_"):
                    baselines[kind.removeprefix("baseline_")] = result
                else:
                    results[size][kind] = result

    pose = pairs[sizes[0]]["T_gt"]
    checkpoint = None if args.checkpoint is None else args.checkpoint.resolve()
    payload = {
        "machine": machine_info(),
        "command": command_line(),
        "clouds": describe_clouds(pose, scan_points, args.seed),
        "sizes": sizes,
        "threads": args.threads,
        "repeats": args.repeats,
        "seed": args.seed,
        "T_gt": pose,
        "checkpoint": None if checkpoint is None else str(
            checkpoint.relative_to(ROOT) if checkpoint.is_relative_to(ROOT) else checkpoint
        ),
        "model": read_manifest(model_dir).provenance.get("name") or str(model_dir),
        "model_architecture": read_manifest(model_dir).model_config.get("architecture", "logdesc"),
        "stem": args.stem,
        "skipped": skipped,
        "memory_metric": "VmHWM of /proc/self/status, KiB (ru_maxrss for reference)",
        "baselines": baselines,
        "results": results,
        "rounds": [round_summary(round_results) for round_results in rounds],
    }
    markdown = markdown_report(payload)
    md_path, json_path = write_report(args.stem, markdown, payload, args.out)
    figure_path = args.out / f"{args.stem}_vs_points.png"
    plot_latency(results, figure_path)
    print(markdown)
    print(f"wrote {md_path}, {json_path}, {figure_path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
