"""What every benchmark script shares: the pairs, the per-pair cache, the summary, the files.

- :func:`modelnet10_test_pairs` builds exactly the pairs of ``training/evaluate.py`` (pair i
  of a protocol is test shape i drawn with ``default_rng([seed, 0, i])``), so the figures of
  both scripts refer to the same 908 pairs per protocol.
- :func:`validation_pairs` builds pairs from the held-out *training* shapes (the training
  run's validation split): the only pairs parameters may be tuned on.
- :class:`ResultCache` appends one JSON line per (pair, method) and is read back on restart,
  so a long run resumes where it stopped.
- :func:`summarize` gives the paper's metrics per method, :func:`write_report` the markdown
  and JSON files in ``benchmarks/results/``.
"""

from __future__ import annotations

import gzip
import json
import math
import os
import platform
import subprocess
import sys
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from hashlib import sha256
from pathlib import Path

import numpy as np
from pykdtree.kdtree import KDTree

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # scripts run as `python benchmarks/x.py` from the project root
    sys.path.insert(0, str(ROOT))

from logdesc_rt.metrics import (  # noqa: E402
    SUCCESS_ROTATION_DEG,
    SUCCESS_TRANSLATION_FRACTION,
    matching_metrics,
    registration_metrics,
    rotation_error_deg,
)
from logdesc_rt.network import bundled_model_dir, read_manifest  # noqa: E402
from logdesc_rt.synthetic import SOURCE_POINTS, Pair, make_pair  # noqa: E402

DATA_ROOT = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "benchmarks" / "results"
DEFAULT_SEED = 1234  # training/evaluate.py's DEFAULT_EVAL_SEED

# The paper's published figures (ModelNet40, its Tables 1-3 and 5), shown beside ours.
PUBLISHED = {
    "noisy": {"label": "published LoGDesc, ModelNet40 (paper Table 2)",
              "source": "LoGDesc paper, Table 2 (ModelNet40, noisy, full overlap)",
              "rmse_r": 0.618, "mae_r": 0.187, "rmse_t": 0.00121, "mae_t": 0.00089},
    "partial": {"label": "published LoGDesc, ModelNet40 (paper Tables 1, 3)",
                "source": "LoGDesc paper, Tables 1 and 3 (ModelNet40, noisy + partial)",
                "rmse_r": 0.774, "mae_r": 0.266, "rmse_t": 0.002, "mae_t": 0.001,
                "precision": 0.920, "accuracy": 0.921, "recall": 0.919, "l_r": 0.95},
    "fpfh_matching_partial": {"label": "published FPFH matching, ModelNet40 (paper Table 1)",
                              "source": "LoGDesc paper, Table 1 (FPFH descriptor, ModelNet40 noisy + partial)",
                              "precision": 0.721, "accuracy": 0.710, "recall": 0.712},
    "bunny": {"label": "published LoGDesc, Stanford Bunny (paper Table 5)",
              "source": "LoGDesc paper, Table 5 (Stanford Bunny, trained on ModelNet40)",
              "rmse_r": 1.01, "mae_r": 0.73, "rmse_t": 0.0272, "mae_t": 0.0310},
}


# ----------------------------------------------------------------------------- pairs
@dataclass(frozen=True)
class BenchmarkPair:
    """A pair with its ground truth and identity in the benchmark.

    Attributes:
        protocol: "clean", "noisy", "partial" (or a dataset-specific label).
        index: pair number within the protocol.
        name: human-readable identity (shape name, scan names).
        source, target: (N, 3) / (M, 3) float64 user-frame clouds.
        T_gt: (4, 4) true pose source -> target.
        gt_match: (N,) int64 true target index per source point, -1 none, -2 ignored (resampled
            protocols: neither matched nor clearly without a counterpart); None if unknown.
        scale: the object's radius in user units (successes are judged relative to it).
    """

    protocol: str
    index: int
    name: str
    source: np.ndarray
    target: np.ndarray
    T_gt: np.ndarray
    gt_match: np.ndarray | None
    scale: float


def _from_synthetic(pair: Pair, protocol: str, index: int, name: str) -> BenchmarkPair:
    return BenchmarkPair(protocol, index, name, pair.source, pair.target, pair.T_gt, pair.gt_match_src,
                         pair.normalization.scale)


def _read_h5(folder: Path, split: str) -> tuple[np.ndarray, list[str]]:
    from training.data import load_modelnet

    data = load_modelnet(folder, split)
    return np.asarray(data.points[:, :SOURCE_POINTS], dtype=np.float64), list(data.shape_ids)


ROTATED_SUFFIX = "_rotated"
ANY_RELATIVE_SUFFIX = "_any_relative"


def modelnet10_test_pairs(
    protocols: Iterable[str], count: int | None = None, seed: int = DEFAULT_SEED, data_root: Path = DATA_ROOT
) -> Iterator[BenchmarkPair]:
    """The evaluation pairs of ``training/evaluate.py``: test shape i, ``default_rng([seed, 0, i])``.

    A protocol with the suffix ``"_rotated"`` (e.g. ``"partial_rotated"``) is the same pair
    with both clouds turned by one uniformly random rotation (``make_pair(...,
    any_orientation=True)``): the paper's protocol keeps the source in the dataset's canonical
    pose, users' scans come in any frame. The suffix ``"_any_relative"`` turns the target of
    that pair once more, alone (``any_relative_rotation=True``): relative rotations of any
    size, where the paper's are at most 45 degrees per axis.
    """
    shapes, names = _read_h5(Path(data_root) / "modelnet10_hdf5_1024", "test")
    count = len(shapes) if count is None else min(count, len(shapes))
    for protocol in protocols:
        apart = protocol.endswith(ANY_RELATIVE_SUFFIX)
        turned = apart or protocol.endswith(ROTATED_SUFFIX)
        base = protocol.removesuffix(ANY_RELATIVE_SUFFIX).removesuffix(ROTATED_SUFFIX)
        for index in range(count):
            pair = make_pair(shapes[index], base, np.random.default_rng([seed, 0, index]), any_orientation=turned,
                             any_relative_rotation=apart)
            yield _from_synthetic(pair, protocol, index, names[index])


def validation_pairs(protocol: str, count: int, seed: int = 0, data_root: Path = DATA_ROOT) -> list[BenchmarkPair]:
    """Pairs from the training run's held-out validation shapes (never the test split)."""
    from training.data import load_training_sources, split_training_shapes

    shapes = split_training_shapes(load_training_sources(data_root))
    pairs = []
    for index in range(min(count, len(shapes.val))):
        pair = make_pair(shapes.val[index], protocol, np.random.default_rng([seed, 7, index]))
        pairs.append(_from_synthetic(pair, protocol, index, shapes.val_ids[index]))
    return pairs


# ----------------------------------------------------------------------------- per-pair records
def pair_record(pair: BenchmarkPair, method: str, result) -> dict:
    """One JSON-able line: the pose, its errors, the time and (if any) matching metrics."""
    T = np.asarray(result.transformation, dtype=np.float64)
    record = {
        "protocol": pair.protocol,
        "index": pair.index,
        "name": pair.name,
        "method": method,
        "T_pred": T.tolist(),
        "T_gt": pair.T_gt.tolist(),
        "rotation_error_deg": float(rotation_error_deg(T[:3, :3], pair.T_gt[:3, :3])),
        "translation_error": float(np.linalg.norm(T[:3, 3] - pair.T_gt[:3, 3])),
        "scale": pair.scale,
        "seconds": float(result.seconds),
        "failed": bool(result.failed),
    }
    if getattr(result, "flagged_success", None) is not None:
        record["flagged_success"] = bool(result.flagged_success)
        record["confidence"] = float(result.confidence)
    if getattr(result, "fast_exit", None) is not None:
        record["fast_exit"] = bool(result.fast_exit)
    if result.pred_match is not None and pair.gt_match is not None:
        metrics = matching_metrics(result.pred_match, pair.gt_match)
        record.update({name: (None if math.isnan(value) else value) for name, value in metrics.items()})
        record["match_count"] = int(np.count_nonzero(np.asarray(result.pred_match) >= 0))
    return record


LEARNED_METHOD_PREFIX = "logdesc_"


def is_learned_method(method: str) -> bool:
    """Whether a method's results depend on the bundled model (all ``logdesc_*`` methods)."""
    return method.startswith(LEARNED_METHOD_PREFIX)


DESCRIPTOR_METHOD_PREFIX = "logdesc_desc_"


def uses_open3d_estimator(method: str) -> bool:
    """Whether a learned method feeds Open3D's estimators, with the baselines' parameters
    (the descriptor-only ``logdesc_desc_*`` methods): its results depend on both."""
    return method.startswith(DESCRIPTOR_METHOD_PREFIX)


REFINED_METHOD_SUFFIX = "_icp"


def is_refined_method(method: str) -> bool:
    """Whether a method's pose is another method's, refined by ICP (all ``*_icp`` methods)."""
    return method.endswith(REFINED_METHOD_SUFFIX)


def bundled_model_id(model_dir: Path | None = None, without_calibration: bool = False) -> str:
    """A short fingerprint of what a model directory makes the runtime do (default: the
    bundled model).

    Derived from its manifest without the descriptive parts (provenance, training config):
    the ONNX files' SHA-256 checksums, every setting the runtime reads from it (geometry,
    normalization, matching), and the runtime configuration it resolves to (its "runtime"
    section, e.g. the success-flag calibration, over the code's defaults:
    ``ModelManifest.runtime_config``). So retraining,
    re-exporting or recalibrating the model changes it, and so does a changed runtime default.
    With ``without_calibration``, the verification settings ("runtime" -> "verification") are
    left out: the identity of the matches, which a recalibration does not change.
    """
    manifest = read_manifest(Path(model_dir) if model_dir is not None else bundled_model_dir())
    used = {k: v for k, v in manifest.to_dict().items() if k not in ("provenance", "model_config")}
    used["runtime"] = manifest.runtime_config().to_dict()
    if without_calibration:
        used["runtime"] = {k: v for k, v in used["runtime"].items() if k != "verification"}
    return sha256(json.dumps(used, sort_keys=True).encode()).hexdigest()[:12]


def model_description(model_dir: Path | None = None) -> str:
    """How a report names the model it measured: the bundled one, or a candidate's folder,
    with the name in its manifest's provenance."""
    folder = Path(model_dir) if model_dir is not None else bundled_model_dir()
    name = read_manifest(folder).provenance.get("name", "unnamed")
    where = "the bundled model" if model_dir is None else f"the model in `{model_dir}`"
    return f"{where} ({name}, id {bundled_model_id(model_dir)})"


class ResultCache:
    """Append-only JSON-lines file of pair records; resumes an interrupted run.

    The repository keeps a gzipped copy (``<name>.jsonl.gz``, a fifth of the size); when only
    that exists it is unpacked next to it first, so the reports can be rebuilt without
    recomputing and new records append to the plain file.

    With ``model_id`` (:func:`bundled_model_id`), records of learned methods are stamped with
    it ("model"), and on loading those of another model (or of none) are dropped from the
    file: they are re-run, while the classical methods' records stay. ``baseline_id``
    (``FpfhParameters.fingerprint()``) does the same for the classical methods ("baseline"):
    one id, or a mapping protocol -> id where a benchmark gives Open3D other parameters for
    each part (``bunny.py``: ModelNet's for the paper protocol, the scans' for real pairs);
    the classical rows refined by ICP (:func:`is_refined_method`) are stamped with
    ``refinement_id`` (``methods.REFINEMENT_ID``) beside it, so that they are re-run when the
    ICP changes while the coarse rows they start from stay; the descriptor-only rows
    (:func:`uses_open3d_estimator`) carry both the model and the baseline parameters.
    """

    def __init__(self, path: Path, fresh: bool = False, model_id: str | None = None,
                 baseline_id: str | Mapping[str, str] | None = None, refinement_id: str | None = None) -> None:
        self.path = Path(path)
        self.model_id = model_id
        self.baseline_id = baseline_id
        self.refinement_id = refinement_id
        self.stale = 0  # records of another model or other baseline parameters, dropped on loading
        self.records: dict[tuple[str, int, str], dict] = {}
        packed = self.path.with_name(self.path.name + ".gz")
        if fresh:  # start over: forget the plain file and do not unpack the kept copy
            self.path.unlink(missing_ok=True)
        elif not self.path.exists() and packed.exists():
            self.path.write_bytes(gzip.decompress(packed.read_bytes()))
        if self.path.exists():
            for line in self.path.read_text().splitlines():
                if line.strip():
                    record = json.loads(line)
                    if self._is_stale(record):
                        self.stale += 1
                        continue
                    self.records[(record["protocol"], record["index"], record["method"])] = record
            if self.stale:  # rewrite without them, so that the kept copy holds one model's results
                self.path.write_text("".join(json.dumps(r) + "\n" for r in self.records.values()))

    def _stamp(self, method: str, protocol: str) -> tuple[str, str | None]:
        """The field a method's records are stamped with, and the value this cache wants."""
        baseline = self.baseline_id.get(protocol) if isinstance(self.baseline_id, Mapping) else self.baseline_id
        if is_learned_method(method):
            if uses_open3d_estimator(method) and self.model_id is not None and baseline is not None:
                return "model", f"{self.model_id}; open3d {baseline}"
            return "model", self.model_id
        if is_refined_method(method) and baseline is not None and self.refinement_id is not None:
            return "baseline", f"{baseline}; icp {self.refinement_id}"
        return "baseline", baseline

    def _is_stale(self, record: dict) -> bool:
        field, wanted = self._stamp(record["method"], record["protocol"])
        return wanted is not None and record.get(field) != wanted

    def has(self, protocol: str, index: int, methods: Iterable[str]) -> bool:
        return all((protocol, index, method) in self.records for method in methods)

    def add(self, records: Iterable[dict]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.path.open("a") as handle:
            for record in records:
                field, wanted = self._stamp(record["method"], record["protocol"])
                if wanted is not None:
                    record = {**record, field: wanted}
                self.records[(record["protocol"], record["index"], record["method"])] = record
                handle.write(json.dumps(record) + "\n")

    def select(self, protocol: str, method: str, indices: Iterable[int]) -> list[dict]:
        return [self.records[(protocol, i, method)] for i in indices if (protocol, i, method) in self.records]

    def pack(self) -> Path:
        """Write the gzipped copy kept in the repository (deterministic: no time stamp)."""
        packed = self.path.with_name(self.path.name + ".gz")
        packed.write_bytes(gzip.compress(self.path.read_bytes(), mtime=0))
        return packed


# ----------------------------------------------------------------------------- summaries
def is_success(record: dict) -> bool:
    """L_R < 5 deg and translation error < 5 % of the object's radius (a pair record)."""
    return bool(record["rotation_error_deg"] < SUCCESS_ROTATION_DEG
                and record["translation_error"] / record["scale"] < SUCCESS_TRANSLATION_FRACTION)


def summarize(records: list[dict]) -> dict[str, float]:
    """The paper's metrics over one method's records on one protocol.

    Keys: rmse_r, mae_r (Euler angles, degrees), rmse_t, mae_t, l_r (mean isotropic rotation
    error), l_r_median, l_t, success (share of pairs with rotation error < 5 deg and
    translation error < 5 % of the object's radius), failed (pairs without a pose),
    precision / accuracy / recall (mean over pairs, NaN where the method has no matches),
    flag_precision / flag_recall (the runtime's success flag: right among the flagged, flagged
    among the right; NaN for methods without a flag), seconds_median and seconds_p90 (the
    slowest 10 % take longer), fast_exit (share of pairs that took the runtime's fast exit; NaN
    for other methods), pairs.
    """
    predicted = np.array([r["T_pred"] for r in records])
    truth = np.array([r["T_gt"] for r in records])
    metrics = registration_metrics(predicted, truth)
    metrics.pop("l_rmse")
    rotation = np.array([r["rotation_error_deg"] for r in records])
    metrics["l_r_median"] = float(np.median(rotation))
    metrics["success"] = float(np.mean([is_success(r) for r in records]))
    metrics["failed"] = int(sum(r["failed"] for r in records))
    for name in ("precision", "accuracy", "recall"):
        values = np.array([r.get(name) for r in records if r.get(name) is not None], dtype=np.float64)
        metrics[name] = float(values.mean()) if len(values) else float("nan")
    flagged = [r for r in records if r.get("flagged_success") is not None]
    metrics["flag_precision"], metrics["flag_recall"] = float("nan"), float("nan")
    if flagged:
        claimed = np.array([r["flagged_success"] for r in flagged])
        right = np.array([is_success(r) for r in flagged])
        if claimed.any():
            metrics["flag_precision"] = float(right[claimed].mean())
        if right.any():
            metrics["flag_recall"] = float(claimed[right].mean())
    seconds = np.array([r["seconds"] for r in records])
    metrics["seconds_median"] = float(np.median(seconds))
    metrics["seconds_p90"] = float(np.percentile(seconds, 90))
    exits = [r["fast_exit"] for r in records if r.get("fast_exit") is not None]
    metrics["fast_exit"] = float(np.mean(exits)) if exits else float("nan")
    metrics["pairs"] = len(records)
    return metrics


OVERLAP_BINS = (0.0, 0.4, 0.6, 0.8, 1.0)  # bin edges; each bin holds its lower edge, the last one also 1
OVERLAP_SPACINGS = 2.0  # "near": within this many median point spacings of the sparser cloud


def overlap_ratio(source: np.ndarray, target: np.ndarray, T_gt: np.ndarray) -> float:
    """How much two clouds see of the same surface, in the true pose.

    A point lies in the overlap when the other cloud, in the true pose, has a point within
    ``OVERLAP_SPACINGS`` median nearest-neighbour spacings (of the sparser of the two clouds,
    so that a denser cloud does not lower the share of a sparse one). The ratio is the smaller
    of the two clouds' shares: a pair where either cloud sees mostly what the other does not is
    a low-overlap pair.

    Args:
        source: (N, 3) source points, user units.
        target: (M, 3) target points, the same units.
        T_gt: (4, 4) true pose source -> target.

    Returns:
        Overlap ratio in [0, 1].
    """
    moved = np.ascontiguousarray(source @ T_gt[:3, :3].T + T_gt[:3, 3])
    target = np.ascontiguousarray(target, dtype=np.float64)
    moved_tree, target_tree = KDTree(moved), KDTree(target)
    spacing = max(float(np.median(tree.query(points, k=2)[0][:, 1]))
                  for tree, points in ((moved_tree, moved), (target_tree, target)))
    near = OVERLAP_SPACINGS * spacing
    source_share = float(np.mean(target_tree.query(moved, k=1)[0] < near))
    target_share = float(np.mean(moved_tree.query(target, k=1)[0] < near))
    return min(source_share, target_share)


def success_by_overlap(records: dict[str, list[dict]], overlaps: dict[int, float]) -> dict[str, dict[str, dict]]:
    """Per method, the pairs and successes in each overlap bin (``OVERLAP_BINS``).

    Args:
        records: method -> its pair records (each with an ``index``).
        overlaps: pair index -> :func:`overlap_ratio`.

    Returns:
        method -> bin label -> {"pairs", "successes", "success"} (success a share, NaN for an
        empty bin).
    """
    edges = list(OVERLAP_BINS)
    table = {}
    for method, method_records in records.items():
        bins = {}
        for lower, upper in zip(edges, edges[1:]):
            last = upper == edges[-1]
            inside = [r for r in method_records
                      if lower <= overlaps[r["index"]] and (overlaps[r["index"]] < upper or last)]
            successes = sum(is_success(r) for r in inside)
            bins[f"{lower:.1f}-{upper:.1f}"] = {
                "pairs": len(inside), "successes": int(successes),
                "success": successes / len(inside) if inside else float("nan")}
        table[method] = bins
    return table


def overlap_markdown_table(table: dict[str, dict[str, dict]]) -> str:
    """Successes / pairs per overlap bin, one row per method (:func:`success_by_overlap`)."""
    labels = list(next(iter(table.values())))
    lines = ["| method | " + " | ".join(f"overlap {label}" for label in labels) + " |",
             "| --- | " + " | ".join("---:" for _ in labels) + " |"]
    for method, bins in table.items():
        cells = [f"{b['successes']}/{b['pairs']}" + (f" ({100 * b['success']:.0f} %)" if b["pairs"] else "")
                 for b in bins.values()]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


COLUMNS = [
    ("RMSE(R)", "rmse_r", "{:.3f}"),
    ("MAE(R)", "mae_r", "{:.3f}"),
    ("RMSE(t)", "rmse_t", "{:.4f}"),
    ("MAE(t)", "mae_t", "{:.4f}"),
    ("L_R mean", "l_r", "{:.2f}"),
    ("L_R median", "l_r_median", "{:.3f}"),
    ("success %", "success", "{:.1f}"),
    ("P %", "precision", "{:.1f}"),
    ("A %", "accuracy", "{:.1f}"),
    ("R %", "recall", "{:.1f}"),
    ("flag P %", "flag_precision", "{:.1f}"),
    ("flag R %", "flag_recall", "{:.1f}"),
    ("ms / pair", "seconds_median", "{:.0f}"),
    ("ms p90", "seconds_p90", "{:.0f}"),
    ("fast exit %", "fast_exit", "{:.0f}"),
    ("failed", "failed", "{:d}"),
    ("pairs", "pairs", "{:d}"),
]
PERCENT = {"success", "precision", "accuracy", "recall", "flag_precision", "flag_recall", "fast_exit"}


def markdown_table(rows: dict[str, dict], label: str = "method") -> str:
    """A markdown table, one row per entry of ``rows`` (name -> metrics)."""
    lines = [f"| {label} | " + " | ".join(title for title, _, _ in COLUMNS) + " |",
             "| --- | " + " | ".join("---:" for _ in COLUMNS) + " |"]
    for name, metrics in rows.items():
        cells = []
        for _, key, fmt in COLUMNS:
            value = metrics.get(key)
            if value is None or (isinstance(value, float) and not math.isfinite(value)):
                cells.append("")
                continue
            if key in PERCENT:
                value = 100.0 * value
            if key in ("seconds_median", "seconds_p90"):
                value = 1e3 * value
            cells.append(fmt.format(value))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def machine_info() -> dict:
    """Hardware and library versions, written into every result file."""
    import onnxruntime

    info = {
        "cpu_count": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "onnxruntime": onnxruntime.__version__,
    }
    try:
        import open3d

        info["open3d"] = open3d.__version__
    except ImportError:
        pass
    try:
        info["commit"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                                        text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    return info


def project_relative(path) -> Path:
    """``path`` relative to the project root when it lies inside it (how reports name files)."""
    path = Path(path).resolve()
    try:
        return path.relative_to(ROOT)
    except ValueError:
        return path


def command_line() -> str:
    """The command that ran this script, as typed from the project root."""
    return " ".join(["python", str(project_relative(sys.argv[0])), *sys.argv[1:]])


def write_report(stem: str, markdown: str, payload: dict, out: Path = RESULTS) -> tuple[Path, Path]:
    """Write ``<stem>.md`` and ``<stem>.json`` into ``out``; return their paths."""
    out.mkdir(parents=True, exist_ok=True)
    md_path, json_path = out / f"{stem}.md", out / f"{stem}.json"
    md_path.write_text(markdown if markdown.endswith("\n") else markdown + "\n")
    json_path.write_text(json.dumps(payload, indent=2, default=_json_default) + "\n")
    return md_path, json_path


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value)}")
