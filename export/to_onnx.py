"""Export a training checkpoint to the runtime's ONNX model directory, and check it.

    python export/to_onnx.py CHECKPOINT.pt [--out DIR] [--opset 17] [--provenance FILE.json]

Writes DIR/descriptor.onnx (edges, points -> descriptors), DIR/matcher.onnx (descriptors and
normals of both clouds -> scores), for the invariant network DIR/matcher_same_size.onnx (the
same function for two clouds of one size, both in one batch) and DIR/manifest.json (configs,
dustbin score, working size, SHA-256 checksums, provenance). The configs and the dustbin score
are also written into each ONNX file's metadata. The graphs have dynamic point counts. Then: ``onnx.checker`` on each
file, and onnxruntime against torch on random inputs and on a real ModelNet10 shape (if the
shared data is present), printing the largest absolute difference against the tolerance; the
script exits with status 1 if any comparison fails. The default DIR is the bundled model
directory, logdesc_rt/models.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import onnx  # noqa: E402
import onnxruntime  # noqa: E402
import torch  # noqa: E402

from logdesc_rt.config import MatchingConfig  # noqa: E402
from logdesc_rt.geometry import compute_geometry  # noqa: E402
from logdesc_rt.network import (  # noqa: E402
    DESCRIPTOR_FILE,
    MANIFEST_NAME,
    MATCHER_FILE,
    POINT_AXES,
    SAME_SIZE_MATCHER_FILE,
    ModelManifest,
    bundled_model_dir,
    sha256_of,
)
from training.checkpoint import CheckpointInfo, load_model  # noqa: E402
from training.model import DescribeModule, MatchScoresModule  # noqa: E402

# Largest acceptable |onnxruntime - torch| for float32 graphs. Descriptors are unit vectors:
# absolute 1e-4. Scores of a trained model grow to tens (sharp matches) after several
# attention layers, where float32 summation order alone moves them by ~1e-5 relative:
# the tolerance is relative to the largest |score|.
DESCRIPTOR_TOLERANCE = 1e-4
SCORE_RELATIVE_TOLERANCE = 1e-4
SHARED_DATA = ROOT.parent / "shared" / "data"


class _Graph(NamedTuple):
    """One exported graph: its file, the module traced, its inputs by name (examples and the
    name of each one's point axis) and its output's name and dynamic axes."""

    file_name: str
    module: torch.nn.Module
    input_names: tuple[str, ...]
    output_name: str
    output_axes: dict[int, str]
    example_inputs: dict[str, torch.Tensor]
    input_axes: dict[str, str]


def export(model, info: CheckpointInfo, out_dir: Path, opset: int, provenance: dict) -> ModelManifest:
    """Write the two ONNX graphs and the manifest into ``out_dir``; return the manifest.

    Args:
        model, info: from :func:`training.checkpoint.load_model` (model in eval mode).
    """
    config = model.config
    k = info.geometry.umbrella_neighbours
    out_dir.mkdir(parents=True, exist_ok=True)
    generator = torch.Generator().manual_seed(0)
    n, m = 64, 48

    def unit(*shape: int) -> torch.Tensor:
        return torch.nn.functional.normalize(torch.randn(*shape, generator=generator), dim=-1)

    # Example inputs by name; each graph takes those its network reads (see
    # LoGDescMatcher.describe_inputs / match_inputs), with dynamic point counts.
    examples = {
        "edges": torch.randn(1, n, k, config.edge_channels, generator=generator),
        "points": torch.randn(1, n, 3, generator=generator),
        "normals": unit(1, n, 3),
        "descriptors_source": unit(1, n, config.descriptor_dim),
        "descriptors_target": unit(1, m, config.descriptor_dim),
        "normals_source": unit(1, n, 3),
        "normals_target": unit(1, m, 3),
        "points_source": torch.randn(1, n, 3, generator=generator),
        "points_target": torch.randn(1, m, 3, generator=generator),
    }
    source_axis, target_axis = POINT_AXES  # the runtime fixes them by name (OnnxNetwork.fixed_points)
    point_axis = {name: (target_axis if name.endswith("_target") else source_axis) for name in examples}
    graphs = [
        _Graph(DESCRIPTOR_FILE, DescribeModule(model), model.describe_inputs, "descriptors", {1: source_axis},
               examples, point_axis),
        _Graph(MATCHER_FILE, MatchScoresModule(model), model.match_inputs, "scores", {1: source_axis, 2: target_axis},
               examples, point_axis),
    ]
    if config.architecture == "invariant":
        # Traced with two clouds of one size, the invariant transformer stacks them in one batch
        # (InvariantTransformer.forward); every input's point axis is the source's.
        same_size = {name: examples[name.replace("_target", "_source")].clone() for name in model.match_inputs}
        graphs.append(_Graph(SAME_SIZE_MATCHER_FILE, MatchScoresModule(model), model.match_inputs, "scores",
                             {1: source_axis, 2: source_axis}, same_size, dict.fromkeys(point_axis, source_axis)))
    with torch.no_grad():
        for graph in graphs:
            dynamic_axes = {name: {1: graph.input_axes[name]} for name in graph.input_names}
            dynamic_axes[graph.output_name] = graph.output_axes
            torch.onnx.export(
                graph.module,
                tuple(graph.example_inputs[name] for name in graph.input_names),
                str(out_dir / graph.file_name),
                input_names=list(graph.input_names),
                output_names=[graph.output_name],
                dynamic_axes=dynamic_axes,
                opset_version=opset,
                dynamo=False,
                # onnxruntime's contrib domain, for the v3 network's fused attention.
                custom_opsets={"com.microsoft": 1},
            )

    matching = MatchingConfig(sinkhorn_iterations=config.sinkhorn_iterations)
    metadata = {
        "logdesc_rt.model_config": json.dumps(config.to_dict()),
        "logdesc_rt.geometry_config": json.dumps(info.geometry.to_dict()),
        "logdesc_rt.normalization_config": json.dumps(info.normalization.to_dict()),
        "logdesc_rt.matching_config": json.dumps(matching.to_dict()),
        "logdesc_rt.dustbin_score": repr(float(model.dustbin_score.detach())),
        "logdesc_rt.points_per_cloud": str(info.points_per_cloud),
    }
    files = [graph.file_name for graph in graphs]
    for name in files:
        graph = onnx.load(str(out_dir / name))
        del graph.metadata_props[:]
        for key, value in metadata.items():
            graph.metadata_props.add(key=key, value=value)
        onnx.checker.check_model(graph, full_check=True)
        onnx.save(graph, str(out_dir / name))
        print(f"onnx.checker: {name} OK (opset {opset})")

    manifest = ModelManifest(
        geometry=info.geometry,
        normalization=info.normalization,
        matching=matching,
        dustbin_score=float(model.dustbin_score.detach()),
        points_per_cloud=info.points_per_cloud,
        descriptor_dim=config.descriptor_dim,
        checksums={name: sha256_of(out_dir / name) for name in files},
        model_config=config.to_dict(),
        provenance={**info.provenance, **provenance},
    )
    (out_dir / MANIFEST_NAME).write_text(json.dumps(manifest.to_dict(), indent=2) + "\n")
    return manifest


def compare_with_torch(model, info: CheckpointInfo, out_dir: Path) -> bool:
    """Run torch and onnxruntime on random and real inputs; print and check the differences."""
    describe = onnxruntime.InferenceSession(str(out_dir / DESCRIPTOR_FILE), providers=["CPUExecutionProvider"])
    match = onnxruntime.InferenceSession(str(out_dir / MATCHER_FILE), providers=["CPUExecutionProvider"])
    same_size_file = out_dir / SAME_SIZE_MATCHER_FILE
    match_same_size = (
        onnxruntime.InferenceSession(str(same_size_file), providers=["CPUExecutionProvider"])
        if same_size_file.is_file()
        else None
    )
    rng = np.random.default_rng(0)
    cases = []
    for n, m in ((300, 200), (1024, 768), (300, 300)):  # sizes unlike the export's 64/48: dynamic axes
        source = rng.normal(size=(n, 3)) * [1.0, 0.7, 0.4]
        target = rng.normal(size=(m, 3)) * [0.8, 0.8, 0.5]
        cases.append((f"random {n}x{m}", source, target))
    shape_file = SHARED_DATA / "modelnet10_hdf5_1024" / "ply_data_test0.h5"
    if shape_file.is_file():
        import h5py

        with h5py.File(shape_file, "r") as handle:
            shape = handle["data"][0].astype(np.float64)
        cases.append(
            ("ModelNet10 test shape 0 vs itself rotated", shape - shape.mean(0), _rotate(shape - shape.mean(0)))
        )
    else:
        print(f"(no real-shape check: {shape_file} not found)")

    passed = True
    for label, source, target in cases:
        geometry_src = compute_geometry(source, info.geometry)
        geometry_tgt = compute_geometry(target, info.geometry)
        as_input = lambda array: np.asarray(array, dtype=np.float32)[None]  # noqa: E731
        describe_src = {"edges": as_input(geometry_src.edges), "points": as_input(source),
                        "normals": as_input(geometry_src.normals)}
        describe_tgt = {"edges": as_input(geometry_tgt.edges), "points": as_input(target),
                        "normals": as_input(geometry_tgt.normals)}
        with torch.no_grad():
            t_desc_src = model.describe(*(torch.from_numpy(describe_src[name]) for name in model.describe_inputs))
            t_desc_tgt = model.describe(*(torch.from_numpy(describe_tgt[name]) for name in model.describe_inputs))
        # Each graph by the inputs it kept: export drops inputs a network never reads (a
        # descriptor-only model's matcher reads no normals and no positions).
        o_desc_src = describe.run(None, {i.name: describe_src[i.name] for i in describe.get_inputs()})[0]
        o_desc_tgt = describe.run(None, {i.name: describe_tgt[i.name] for i in describe.get_inputs()})[0]
        match_feeds = {
            "descriptors_source": o_desc_src, "descriptors_target": o_desc_tgt,
            "normals_source": describe_src["normals"], "normals_target": describe_tgt["normals"],
            "points_source": describe_src["points"], "points_target": describe_tgt["points"],
        }
        with torch.no_grad():
            # torch gets onnxruntime's descriptors too, so the scores compare the matcher alone.
            t_scores = model.match_scores(*(torch.from_numpy(match_feeds[name]) for name in model.match_inputs))
        o_scores = match.run(None, {i.name: match_feeds[i.name] for i in match.get_inputs()})[0]
        descriptor_error = max(
            np.abs(o_desc_src - t_desc_src.numpy()).max(), np.abs(o_desc_tgt - t_desc_tgt.numpy()).max()
        )
        score_scale = float(np.abs(t_scores.numpy()).max())
        score_error = float(np.abs(o_scores - t_scores.numpy()).max())
        if match_same_size is not None and len(source) == len(target):
            o_same = match_same_size.run(None, {i.name: match_feeds[i.name] for i in match_same_size.get_inputs()})[0]
            score_error = max(score_error, float(np.abs(o_same - t_scores.numpy()).max()))
            label += f" (and {SAME_SIZE_MATCHER_FILE})"
        score_tolerance = SCORE_RELATIVE_TOLERANCE * max(score_scale, 1.0)
        ok = descriptor_error <= DESCRIPTOR_TOLERANCE and score_error <= score_tolerance
        passed &= ok
        print(
            f"{label}: max |ort - torch| descriptors {descriptor_error:.2e} (tol {DESCRIPTOR_TOLERANCE:.0e}), "
            f"scores {score_error:.2e} (tol {score_tolerance:.1e} = {SCORE_RELATIVE_TOLERANCE:.0e} x max|score| "
            f"{score_scale:.1f}) -> {'OK' if ok else 'FAIL'}"
        )
    return passed


def _rotate(points: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return points @ Rotation.from_euler("zyx", [30.0, 20.0, 10.0], degrees=True).as_matrix().T


def checkpoint_name(path: Path) -> str:
    """The checkpoint's path relative to the repository root (POSIX), or as given if outside it."""
    resolved = Path(path).resolve()
    return resolved.relative_to(ROOT).as_posix() if resolved.is_relative_to(ROOT) else str(path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Export a logdesc-rt checkpoint to ONNX and check it.")
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--out", type=Path, default=None, help="model directory (default: the bundled one)")
    parser.add_argument("--opset", type=int, default=17)
    parser.add_argument("--provenance", type=Path, default=None, help="JSON merged into the manifest's provenance")
    args = parser.parse_args(argv)
    out_dir = args.out or bundled_model_dir()
    provenance = json.loads(args.provenance.read_text()) if args.provenance else {}
    # Which file the ONNX files must match (tests/test_export.py checks the bundled model against it).
    provenance["checkpoint_file"] = checkpoint_name(args.checkpoint)
    model, info = load_model(args.checkpoint)
    export(model, info, out_dir, args.opset, provenance)
    ok = compare_with_torch(model, info, out_dir)
    print(f"model written to {out_dir}: {'all checks passed' if ok else 'PARITY CHECK FAILED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
