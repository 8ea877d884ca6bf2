"""The public API with the bundled model: accuracy, determinism, subsampling, bad input."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

import logdesc_rt
from logdesc_rt import Registrar
from logdesc_rt.demo import make_demo_pair
from logdesc_rt.denormals import X86_64
from logdesc_rt.errors import ModelFileError, NonFinitePointsError, PointCloudFileError, TooFewPointsError
from logdesc_rt.metrics import rotation_error_deg
from logdesc_rt.network import bundled_model_dir
from logdesc_rt.pose.candidates import DESCRIPTOR_PREFIX
from logdesc_rt.synthetic import make_pair
from logdesc_rt.verification import TURNED_OVER, UNEXPLAINED_PREFIX


@pytest.fixture(scope="module")
def registrar() -> Registrar:
    return Registrar()


@pytest.fixture(scope="module")
def demo_pair():
    return make_demo_pair()


def test_demo_pair_is_registered_within_two_degrees(registrar, demo_pair):
    """Noisy, partial (768 of 1024 points, independent cuts): the bundled model measured ~1 deg here."""
    result = registrar.register(demo_pair.source, demo_pair.target)
    truth = demo_pair.true_transformation
    assert rotation_error_deg(result.rotation, truth[:3, :3]) < 2.0
    assert np.linalg.norm(result.translation - truth[:3, 3]) < 0.05
    assert result.transformation.shape == (4, 4)
    assert np.allclose(result.transformation[3], [0, 0, 0, 1])
    assert len(result.correspondences) == len(result.confidences) > 50
    assert np.all((result.confidences > 0) & (result.confidences <= 1))
    assert 0.5 < result.fitness <= 1.0
    assert {"geometry", "descriptors", "matcher", "matching", "pose", "total"} <= set(result.timings)
    assert result.subsampled == (len(demo_pair.source) > registrar.max_points)
    assert result.source_points_used == min(len(demo_pair.source), registrar.max_points)


def test_icp_refinement_tightens_the_pose(registrar, demo_pair):
    truth = demo_pair.true_transformation[:3, :3]
    coarse = registrar.register(demo_pair.source, demo_pair.target)
    refined = registrar.register(demo_pair.source, demo_pair.target, refine="point_to_plane")
    assert np.array_equal(refined.transformation_before_refinement, coarse.transformation)
    assert rotation_error_deg(refined.rotation, truth) < 0.5
    # Point-to-plane ICP minimises distances to the target's planes, not the point-to-point
    # RMSE reported: at a pose already this close the RMSE may move by a fraction of a percent.
    assert refined.inlier_rmse <= 1.01 * coarse.inlier_rmse
    assert refined.fitness >= coarse.fitness - 0.01


@pytest.mark.parametrize(("estimator", "bound_deg"), [("svd", 15.0), ("ransac", 5.0), ("core", 5.0)])
def test_other_estimators(registrar, demo_pair, estimator, bound_deg):
    """RANSAC is robust; plain SVD fits every match, wrong ones included (measured 7.8 deg)."""
    result = registrar.register(demo_pair.source, demo_pair.target, estimator=estimator)
    assert rotation_error_deg(result.rotation, demo_pair.true_transformation[:3, :3]) < bound_deg


def test_the_candidate_set_is_the_configs(registrar, demo_pair):
    """VerificationConfig.candidates (on the matcher's matches) and .descriptor_consensus (on the
    descriptors' own) decide which estimators are verified: with "core" among them, its pose is
    among the hypotheses; an unknown name is refused."""
    default = registrar.register(demo_pair.source, demo_pair.target, thorough=True)
    names = {name for hypothesis in default.verification.hypotheses for name in hypothesis.estimators}
    # The second look's names: the turn-overs and each candidate on the unexplained matches.
    names = {name.removeprefix(UNEXPLAINED_PREFIX) for name in names if name != TURNED_OVER}
    on_descriptors = {name.removeprefix(DESCRIPTOR_PREFIX) for name in names if name.startswith(DESCRIPTOR_PREFIX)}
    on_matches = {name for name in names if not name.startswith(DESCRIPTOR_PREFIX)}
    assert on_matches <= set(registrar.config.verification.candidates)
    assert on_descriptors <= set(registrar.config.verification.descriptor_consensus)
    candidates = ("fsr", "ransac", "svd", "top_k", "core")
    widened = registrar.register(
        demo_pair.source, demo_pair.target, config={"verification": {"candidates": candidates}}, thorough=True
    )
    assert "core" in {name for hypothesis in widened.verification.hypotheses for name in hypothesis.estimators}
    with pytest.raises(ValueError, match="candidates"):
        registrar.register(demo_pair.source, demo_pair.target, config={"verification": {"candidates": ["magic"]}})


def test_match_then_pose_equals_register(registrar, demo_pair):
    """``Registrar.match`` + ``PairMatches.pose`` is exactly what ``register`` returns."""
    pair = registrar.match(demo_pair.source, demo_pair.target)
    for estimator in ("fsr", "svd", "ransac"):
        result = registrar.register(demo_pair.source, demo_pair.target, estimator=estimator, seed=3)
        assert np.array_equal(pair.pose(estimator, seed=3), result.transformation)
    assert np.array_equal(pair.correspondences, result.correspondences)
    assert pair.source_descriptors.shape == (len(pair.source_index), registrar.manifest.descriptor_dim)
    assert np.allclose(np.linalg.norm(pair.source_descriptors, axis=1), 1.0, atol=1e-4)
    assert pair.scores.shape == (len(pair.source_index), len(pair.target_index))
    with pytest.raises(ValueError, match="estimator"):
        pair.pose("magic")


def test_register_matches_finishes_what_match_started(registrar, demo_pair):
    """``register_matches(match(s, t), **kw)`` is ``register(s, t, **kw)``, networks run once."""
    pair = registrar.match(demo_pair.source, demo_pair.target)
    for options in ({}, {"estimator": "svd", "seed": 2}, {"refine": "point_to_plane"}):
        whole = registrar.register(demo_pair.source, demo_pair.target, **options)
        finished = registrar.register_matches(pair, **options)
        assert np.array_equal(finished.transformation, whole.transformation), options
        assert (finished.success, finished.confidence, finished.pose_estimator) == (
            whole.success, whole.confidence, whole.pose_estimator
        )
        assert finished.config == whole.config


def _resampled_partial_pair(seed: int):
    """A resampled partial pair of the demo shape (the clouds share no sample), any rotation."""
    from logdesc_rt.demo import SOURCE_POINTS, demo_object

    return make_pair(demo_object(SOURCE_POINTS, 0), "resampled_partial", np.random.default_rng(seed),
                     any_orientation=True, any_relative_rotation=True)


SECOND_DRAW = {"subsampling": {"second_draw": True}}
VOXEL_DRAW_ONLY = {"subsampling": {"method": "voxel"}}


def test_a_claimed_pair_is_drawn_once(registrar, demo_pair):
    result = registrar.register(demo_pair.source, demo_pair.target, config=SECOND_DRAW)
    assert result.success and result.draws == 1 and "second_draw" not in result.timings


@pytest.mark.parametrize("seed", [24, 2])
def test_the_second_draw_keeps_the_more_confident_result(registrar, seed):
    """With the second draw asked for, a pair unclaimed by the first (farthest-point) draw is
    matched again on voxel working subsets and the more confident result returned, exactly as
    each draw alone gives it; the default draws once.
    Seed 24 (found with the bundled model): the first draw's pose is right but unverified
    (confidence 0), the voxel draw's is right and claimed. Seed 2: neither is claimed and the
    first is the more confident, so it stays."""
    pair = _resampled_partial_pair(seed)
    first = registrar.register(pair.source, pair.target)
    voxel = registrar.register(pair.source, pair.target, config=VOXEL_DRAW_ONLY)
    both = registrar.register(pair.source, pair.target, config=SECOND_DRAW)
    assert not first.success and first.draws == 1
    assert both.draws == 2
    kept = voxel if voxel.confidence > first.confidence else first
    assert np.array_equal(both.transformation, kept.transformation)
    assert (both.success, both.confidence) == (kept.success, kept.confidence)
    assert both.config.subsampling.method == kept.config.subsampling.method
    assert both.timings["second_draw"] > 0
    assert both.timings["total"] == pytest.approx(sum(v for k, v in both.timings.items() if k != "total"))
    if seed == 24:
        assert both.success and both.config.subsampling.method == "voxel"
        assert rotation_error_deg(both.rotation, pair.T_gt[:3, :3]) < 5.0
    again = registrar.register(pair.source, pair.target, config=SECOND_DRAW)
    assert np.array_equal(again.transformation, both.transformation) and again.confidence == both.confidence
    drawing = Registrar(config=SECOND_DRAW)  # register_matches applies its options over the pair's config
    finished = drawing.register_matches(drawing.match(pair.source, pair.target))
    assert np.array_equal(finished.transformation, both.transformation) and finished.draws == 2


def test_no_second_draw_when_both_draws_would_be_the_same_points(registrar, demo_pair):
    """Clouds no larger than the working size are their own working subsets by either method."""
    from .shapes import twisted_bar

    small = demo_pair.source[: registrar.max_points - 20]
    result = registrar.register(small, twisted_bar(registrar.max_points - 20), config=SECOND_DRAW)
    assert not result.success and result.draws == 1 and "second_draw" not in result.timings


def test_prepare_is_where_match_starts(registrar, demo_pair):
    """``Registrar.prepare`` gives the clouds and geometry ``match`` feeds to the networks."""
    from logdesc_rt import compute_geometry

    prepared = registrar.prepare(demo_pair.source, demo_pair.target)
    assert set(prepared.timings) == {"load", "subsample", "geometry"}
    expected = prepared.normalization.source_to_network(demo_pair.source[prepared.source_index])
    assert np.array_equal(prepared.source_network, expected)
    assert np.array_equal(prepared.source_geometry.edges, compute_geometry(expected, registrar.manifest.geometry).edges)
    pair = registrar.match(demo_pair.source, demo_pair.target)
    assert np.array_equal(pair.target_network, prepared.target_network)
    descriptors = registrar.network.describe(
        prepared.source_geometry.edges, prepared.source_network, prepared.source_geometry.normals
    )
    assert np.array_equal(pair.source_descriptors, descriptors)
    # a larger working size than the cloud: nothing is subsampled (the latency benchmark's use)
    big = Registrar(max_points=4 * len(demo_pair.source)).prepare(demo_pair.source, demo_pair.target)
    assert len(big.source_index) == len(demo_pair.source) and len(big.target_index) == len(demo_pair.target)


def test_user_units_and_placement_do_not_matter(registrar, demo_pair):
    """A metre-scale copy placed far away gives the same rotation and the scaled translation."""
    scale, offset = 0.05, np.array([120.0, -30.0, 4.0])
    base = registrar.register(demo_pair.source, demo_pair.target)
    moved = registrar.register(demo_pair.source * scale + offset, demo_pair.target * scale + offset)
    assert np.allclose(moved.rotation, base.rotation, atol=1e-4)
    expected_translation = scale * base.translation + offset - base.rotation @ offset
    assert np.allclose(moved.translation, expected_translation, atol=1e-4 * scale + 1e-9)


def test_same_input_same_output(registrar, demo_pair):
    first = registrar.register(demo_pair.source, demo_pair.target)
    second = registrar.register(demo_pair.source.copy(), demo_pair.target.copy())
    assert np.array_equal(first.transformation, second.transformation)
    assert np.array_equal(first.correspondences, second.correspondences)


def test_large_clouds_are_subsampled_and_indices_refer_to_the_input(registrar):
    rng = np.random.default_rng(0)
    shape = make_demo_pair().source
    dense = np.repeat(shape, 4, axis=0) + rng.normal(scale=0.003, size=(4 * len(shape), 3))
    pose = make_demo_pair().true_transformation
    target = dense @ pose[:3, :3].T + pose[:3, 3]
    result = registrar.register(dense, target)
    assert result.subsampled and result.source_points_used == registrar.max_points
    assert result.correspondences[:, 0].max() < len(dense)
    matched_source = dense[result.correspondences[:, 0]] @ pose[:3, :3].T + pose[:3, 3]
    # Most matches are true neighbours in the dense cloud.
    distance = np.linalg.norm(matched_source - target[result.correspondences[:, 1]], axis=1)
    assert np.median(distance) < 0.05
    assert rotation_error_deg(result.rotation, pose[:3, :3]) < 3.0


def test_voxel_subsampling_keeps_the_working_size():
    registrar = Registrar(subsampling="voxel")
    pair = make_demo_pair()
    rng = np.random.default_rng(1)
    dense = np.repeat(pair.source, 5, axis=0) + rng.normal(scale=0.003, size=(5 * len(pair.source), 3))
    result = registrar.register(dense, pair.target)
    assert result.subsampled and result.source_points_used == registrar.max_points
    assert result.target_points_used == min(len(pair.target), registrar.max_points)
    assert rotation_error_deg(result.rotation, pair.true_transformation[:3, :3]) < 3.0


def test_describe_returns_unit_descriptors(registrar, demo_pair):
    described = registrar.describe(demo_pair.source)
    count = min(len(demo_pair.source), registrar.max_points)  # the working subset of a larger cloud
    assert described.descriptors.shape == (count, registrar.manifest.descriptor_dim) == (len(described.indices), 96)
    assert np.allclose(np.linalg.norm(described.descriptors, axis=1), 1.0, atol=1e-4)


def test_modelnet10_test_pairs_noisy_partial(registrar, shared_data):
    """First 24 ModelNet10 test shapes, paper's noisy-partial protocol, fixed seed.

    Bound: median rotation error below 2 degrees and at least 75 % of pairs below 5 degrees.
    The shipped model validated at a median of 0.74 deg and 89 % under 5 deg on partial
    pairs (128 validation pairs), so the bound leaves room for a small sample, not for a
    broken pipeline (an untrained or mis-normalised one gives tens of degrees).
    """
    import h5py

    with h5py.File(shared_data / "modelnet10_hdf5_1024" / "ply_data_test0.h5", "r") as handle:
        shapes = handle["data"][:24].astype(np.float64)
    errors = []
    for index, shape in enumerate(shapes):
        pair = make_pair(shape, "partial", np.random.default_rng([1234, 0, index]))
        result = registrar.register(pair.source, pair.target)
        errors.append(rotation_error_deg(result.rotation, pair.T_gt[:3, :3]))
    errors = np.array(errors)
    assert np.median(errors) < 2.0, errors
    assert np.mean(errors < 5.0) >= 0.75, errors


def test_files_are_accepted(registrar, demo_pair, tmp_path):
    source_path, target_path = tmp_path / "source.ply", tmp_path / "target.xyz"
    logdesc_rt.write_point_cloud(source_path, demo_pair.source)
    logdesc_rt.write_point_cloud(target_path, demo_pair.target)
    from_files = registrar.register(source_path, str(target_path))
    from_arrays = registrar.register(demo_pair.source, demo_pair.target)
    assert np.allclose(from_files.transformation, from_arrays.transformation)


@pytest.mark.parametrize(
    ("source", "error", "message"),
    [
        (np.full((100, 3), np.nan), NonFinitePointsError, "source"),
        (np.random.default_rng(0).normal(size=(10, 3)), TooFewPointsError, "at least 21"),
        ("/nonexistent/cloud.ply", PointCloudFileError, "nonexistent"),
    ],
)
def test_bad_input_raises_named_errors(registrar, demo_pair, source, error, message):
    with pytest.raises(error, match=message):
        registrar.register(source, demo_pair.target)


def test_bad_options_raise(registrar, demo_pair):
    with pytest.raises(ValueError, match="estimator"):
        registrar.register(demo_pair.source, demo_pair.target, estimator="magic")
    with pytest.raises(ValueError, match="refine"):
        registrar.register(demo_pair.source, demo_pair.target, refine="nope")


def test_corrupt_or_missing_model_files_are_refused(tmp_path):
    model_dir = tmp_path / "model"
    shutil.copytree(bundled_model_dir(), model_dir)
    Registrar(model_dir)  # an intact copy loads
    data = bytearray((model_dir / "matcher.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (model_dir / "matcher.onnx").write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match="checksum mismatch"):
        Registrar(model_dir)
    (model_dir / "matcher.onnx").unlink()
    with pytest.raises(ModelFileError, match="missing"):
        Registrar(model_dir)
    with pytest.raises(ModelFileError, match="no model manifest"):
        Registrar(tmp_path)


_DENORMAL_PROBE = r"""
import numpy as np
from logdesc_rt import Registrar
from logdesc_rt.demo import make_demo_pair
from logdesc_rt.network import network_thread, second_network_thread

def flushes(x):  # True when this thread treats denormal floats as zero (FTZ / DAZ)
    return bool((np.array([1e-40], dtype=np.float32) * np.float32(x))[0] == 0.0)

pair = make_demo_pair()
source, target = pair.source, pair.target
registrar = Registrar(threads=2)
first = registrar.register(source, target).transformation
second = Registrar(threads=2).register(source, target).transformation  # a second model, same threads
side_by_side = registrar.network._side_by_side
print(flushes(1.0), network_thread().submit(flushes, 1.0).result(),
      second_network_thread().submit(flushes, 1.0).result() if side_by_side else "not-used",
      float(np.abs(first - second).max()))
"""


def test_the_networks_flush_denormals_on_their_own_thread_only():
    """onnxruntime's flush-to-zero mode (the networks' speed, see OnnxNetwork) must not leak into
    the caller's threads, must hold on the thread that runs the graphs, and changes nothing in
    the result. A fresh process: the mode is set by the first onnxruntime session it creates."""
    import subprocess
    import sys

    completed = subprocess.run(
        [sys.executable, "-c", _DENORMAL_PROBE], capture_output=True, text=True, timeout=300, check=True
    )
    caller_flushes, network_flushes, second_flushes, difference = completed.stdout.split()
    assert caller_flushes == "False", "the caller's thread lost IEEE denormals"
    assert network_flushes == "True", "the network thread does not flush denormals (the slow path)"
    # The second network thread runs one cloud's descriptor beside the first (x86-64).
    assert second_flushes == ("True" if X86_64 else "not-used")
    assert float(difference) == 0.0


def test_fitness_is_computed_on_a_bounded_seeded_subset_of_the_source(registrar, demo_pair):
    """Every source point is scored up to evaluation_points; beyond, a seeded subset of that many,
    each against the whole target, and the result says how many: the same figures as
    evaluate_registration on that subset, and the same again for the same seed."""
    from logdesc_rt.pose import evaluate_registration
    from logdesc_rt.sampling import seeded_subset

    whole = registrar.register(demo_pair.source, demo_pair.target)
    assert whole.fitness_points == len(demo_pair.source)
    expected = evaluate_registration(
        demo_pair.source, demo_pair.target, whole.max_correspondence_distance, whole.transformation
    )
    assert whole.fitness == expected.fitness

    bounded_config = {"refinement": {"evaluation_points": 100}}
    bounded = registrar.register(demo_pair.source, demo_pair.target, config=bounded_config)
    assert bounded.fitness_points == 100
    assert np.array_equal(bounded.transformation, whole.transformation)
    subset = seeded_subset(len(demo_pair.source), 100, np.random.default_rng(bounded.config.refinement.seed))
    on_subset = evaluate_registration(
        demo_pair.source[subset], demo_pair.target, bounded.max_correspondence_distance, bounded.transformation
    )
    assert bounded.fitness == on_subset.fitness
    assert bounded.inlier_rmse == on_subset.inlier_rmse
    again = registrar.register(demo_pair.source, demo_pair.target, config=bounded_config)
    assert again.fitness == bounded.fitness
    assert bounded.to_dict()["fitness_points"] == 100


def test_after_icp_the_fitness_is_icps_own_final_evaluation_on_the_same_subset(registrar, demo_pair):
    """With ICP, the result's fitness and RMSE come from ICP's last query (its source subset is
    the evaluation's when max_source_points == evaluation_points): the figures
    evaluate_registration gives on that subset, for 1,024 points and for a subset of 300; with
    the two sizes apart, evaluate_registration's own."""
    from logdesc_rt.pose import evaluate_registration
    from logdesc_rt.sampling import seeded_subset

    for count in (20_000, 300):
        config = {"refinement": {"max_source_points": count, "evaluation_points": count}}
        result = registrar.register(demo_pair.source, demo_pair.target, refine="point_to_plane", config=config)
        subset = seeded_subset(len(demo_pair.source), count, np.random.default_rng(result.config.refinement.seed))
        expected = evaluate_registration(
            demo_pair.source[subset], demo_pair.target, result.max_correspondence_distance, result.transformation
        )
        assert result.fitness_points == len(subset)
        assert result.fitness == pytest.approx(expected.fitness, abs=1.5 / len(subset))
        assert result.inlier_rmse == pytest.approx(expected.inlier_rmse, rel=1e-6)
    apart = {"refinement": {"max_source_points": 300, "evaluation_points": 200}}
    result = registrar.register(demo_pair.source, demo_pair.target, refine="point_to_plane", config=apart)
    subset = seeded_subset(len(demo_pair.source), 200, np.random.default_rng(result.config.refinement.seed))
    expected = evaluate_registration(
        demo_pair.source[subset], demo_pair.target, result.max_correspondence_distance, result.transformation
    )
    assert (result.fitness, result.inlier_rmse) == (expected.fitness, expected.inlier_rmse)


def test_the_networks_at_the_working_size_run_fixed_size_sessions_that_agree_with_the_dynamic_ones(
    registrar, demo_pair
):
    """Clouds cut to the working size reach the networks through sessions with fixed point axes
    (OnnxNetwork.fixed_points); their outputs are the dynamic graphs' within float32 rounding,
    and any other size runs the dynamic sessions."""
    from logdesc_rt.network import DESCRIPTOR_FILE, MATCHER_FILE, SAME_SIZE_MATCHER_FILE, OnnxNetwork

    prepared = registrar.prepare(demo_pair.source, demo_pair.target)
    working = registrar.max_points
    assert len(prepared.source_index) == len(prepared.target_index) == working
    fixed = OnnxNetwork(fixed_points=working)
    dynamic = OnnxNetwork()
    source, target = prepared.source_geometry, prepared.target_geometry

    def outputs(network: OnnxNetwork) -> tuple[np.ndarray, np.ndarray]:
        descriptors = [network.describe(g.edges, p, g.normals) for g, p in
                       ((source, prepared.source_network), (target, prepared.target_network))]
        scores = network.match_scores(*descriptors, source.normals, target.normals,
                                      prepared.source_network, prepared.target_network)
        return descriptors[0], scores

    for fixed_output, dynamic_output in zip(outputs(fixed), outputs(dynamic), strict=True):
        # float32 rounding through the layers: within 2e-5 of the output's largest magnitude
        assert np.abs(fixed_output - dynamic_output).max() <= 2e-5 * np.abs(dynamic_output).max()
    # Two clouds of the working size go through the same-size matcher graph (both in one batch).
    assert set(fixed._fixed_sessions) == {DESCRIPTOR_FILE, SAME_SIZE_MATCHER_FILE} and not dynamic._fixed_sessions
    assert set(dynamic._sessions) == {DESCRIPTOR_FILE, MATCHER_FILE, SAME_SIZE_MATCHER_FILE}

    smaller = OnnxNetwork(fixed_points=working)
    smaller.describe(source.edges[:200], prepared.source_network[:200], source.normals[:200])
    assert not smaller._fixed_sessions


def test_the_same_size_matcher_graph_scores_as_the_general_one(registrar, demo_pair):
    """Two clouds of one size go through matcher_same_size.onnx (both in one batch), whose
    scores are matcher.onnx's within float32 rounding; clouds of two sizes through matcher.onnx.
    A model without the graph (its manifest does not list it) uses matcher.onnx for both."""
    from logdesc_rt.network import MATCHER_FILE, SAME_SIZE_MATCHER_FILE, OnnxNetwork

    prepared = registrar.prepare(demo_pair.source, demo_pair.target)
    source, target = prepared.source_geometry, prepared.target_geometry
    describer = OnnxNetwork()
    inputs = [describer.describe(geometry.edges, points, geometry.normals) for geometry, points in
              ((source, prepared.source_network), (target, prepared.target_network))]
    arguments = (*inputs, source.normals, target.normals, prepared.source_network, prepared.target_network)
    with_graph, without_graph = OnnxNetwork(), OnnxNetwork()
    del without_graph.manifest.checksums[SAME_SIZE_MATCHER_FILE]
    same_size, general = with_graph.match_scores(*arguments), without_graph.match_scores(*arguments)
    assert SAME_SIZE_MATCHER_FILE in with_graph._sessions and SAME_SIZE_MATCHER_FILE not in without_graph._sessions
    assert np.abs(same_size - general).max() <= 2e-5 * np.abs(general).max()
    cut = (inputs[0], inputs[1][:300], source.normals, target.normals[:300], prepared.source_network,
           prepared.target_network[:300])
    fresh = OnnxNetwork()
    assert fresh.match_scores(*cut).shape == (len(inputs[0]), 300)
    assert set(fresh._sessions) == {"descriptor.onnx", MATCHER_FILE}


def _working_size_clouds(registrar, demo_pair) -> list[dict[str, np.ndarray]]:
    """The demo pair's two clouds at the working size, as OnnxNetwork.describe's arguments."""
    prepared = registrar.prepare(demo_pair.source, demo_pair.target)
    return [
        {"edges": geometry.edges, "points": points, "normals": geometry.normals}
        for geometry, points in ((prepared.source_geometry, prepared.source_network),
                                 (prepared.target_geometry, prepared.target_network))
    ]


def test_a_pairs_descriptors_side_by_side_are_each_clouds_own(registrar, demo_pair):
    """describe_pair runs two working-size clouds at once on two threads with half the
    intra-op threads each (x86-64, two threads or more); its descriptors are describe's of each
    cloud within float32 rounding, and clouds of another size go one after the other."""
    from logdesc_rt.network import OnnxNetwork

    clouds = _working_size_clouds(registrar, demo_pair)
    network = OnnxNetwork(threads=2, fixed_points=registrar.max_points)
    paired = network.describe_pair(*clouds)
    assert network._side_by_side == X86_64
    alone = [OnnxNetwork(threads=2).describe(**cloud) for cloud in clouds]
    for together, single in zip(paired, alone, strict=True):
        assert together.shape == single.shape
        assert np.abs(together - single).max() <= 2e-5
    one_thread = OnnxNetwork(threads=1, fixed_points=registrar.max_points)
    one_thread.describe_pair(*clouds)
    assert one_thread._side_by_side is False  # one thread: nothing to share out
    cut = [{name: array[:200] for name, array in cloud.items()} for cloud in clouds]
    unfixed = OnnxNetwork(threads=2, fixed_points=registrar.max_points)
    unfixed.describe_pair(*cut)
    assert unfixed._side_by_side is None and unfixed._half_descriptor is None


def test_descriptors_go_one_after_the_other_where_flush_to_zero_cannot_be_set(registrar, demo_pair, monkeypatch):
    """If this package cannot set flush-to-zero (another platform, a numba that fails), the two
    clouds go through the descriptor one after the other, with the same descriptors."""
    import logdesc_rt.denormals
    from logdesc_rt.network import OnnxNetwork

    def broken() -> bool:
        raise RuntimeError("no MXCSR here")

    monkeypatch.setattr(logdesc_rt.denormals, "flush_denormals_on_this_thread", broken)
    clouds = _working_size_clouds(registrar, demo_pair)
    network = OnnxNetwork(threads=2, fixed_points=registrar.max_points)
    paired = network.describe_pair(*clouds)
    assert network._side_by_side is False and network._half_descriptor is None
    for together, cloud in zip(paired, clouds, strict=True):
        np.testing.assert_array_equal(together, network.describe(**cloud))
