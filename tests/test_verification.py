"""Verified hypotheses, the success flag and the runtime configuration."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from logdesc_rt import Registrar
from logdesc_rt.config import (
    VERIFICATION_FEATURES,
    FsrConfig,
    RefinementConfig,
    RuntimeConfig,
    VerificationConfig,
)
from logdesc_rt.demo import make_demo_pair
from logdesc_rt.matching import mutual_nearest_descriptors
from logdesc_rt.metrics import rotation_error_deg
from logdesc_rt.pose.candidates import candidate_poses, descriptor_candidate_poses, unexplained_candidate_poses
from logdesc_rt.verification import PoseVerifier, logistic_confidence

from .bunny import bunny_pair


@pytest.fixture(scope="module")
def registrar() -> Registrar:
    return Registrar()


@pytest.fixture(scope="module")
def demo_pair():
    return make_demo_pair()


def _turned(pose: np.ndarray, degrees: float, about: np.ndarray) -> np.ndarray:
    """``pose`` followed by a turn of ``degrees`` about the x axis through ``about``."""
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("x", degrees, degrees=True).as_matrix()
    turn[:3, 3] = about - turn[:3, :3] @ about
    return turn @ pose


def test_candidates_recover_an_exact_pose_despite_outliers():
    rng = np.random.default_rng(5)
    source = rng.uniform(-1, 1, size=(200, 3))
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_euler("zyx", [30, -20, 10], degrees=True).as_matrix()
    truth[:3, 3] = [0.2, -0.1, 0.3]
    target = source @ truth[:3, :3].T + truth[:3, 3]
    target[:60] = rng.uniform(-1, 1, size=(60, 3))  # 30 % wrong matches
    candidates = dict(candidate_poses(source, target, np.full(200, 0.5)))
    assert set(candidates) == set(VerificationConfig().candidates)
    for name in ("fsr", "ransac", "core"):
        assert rotation_error_deg(candidates[name][:3, :3], truth[:3, :3]) < 1e-4, name  # arccos resolves ~1e-6 deg
    # Plain SVD fits the wrong matches too: the reason it is only one candidate among several.
    assert rotation_error_deg(candidates["svd"][:3, :3], truth[:3, :3]) > 1.0


def test_confidence_separates_the_true_pose_from_a_wrong_one(registrar, demo_pair):
    """On the demo pair the true pose is confidently right, the same pose turned 90 deg is not
    (with the calibration that ships: the bundled model's)."""
    source, target, truth = demo_pair.source, demo_pair.target, demo_pair.true_transformation
    scale = 1.0  # the demo pair lives in the unit sphere
    config = registrar.config.verification
    verifier = PoseVerifier(source, target, source[:3], target[:3], np.ones(3), scale, config)
    right = logistic_confidence(verifier.features(truth, agreement=1.0), config)
    wrong = logistic_confidence(verifier.features(_turned(truth, 90.0, target.mean(axis=0)), agreement=1.0), config)
    assert right >= config.success_threshold > wrong
    assert len(verifier.features(truth)) == len(VERIFICATION_FEATURES)


def test_in_range_pair_is_a_success(registrar, demo_pair):
    result = registrar.register(demo_pair.source, demo_pair.target)
    assert result.success and result.confidence >= result.config.verification.success_threshold
    assert rotation_error_deg(result.rotation, demo_pair.true_transformation[:3, :3]) < 5.0
    assert result.pose_estimator in result.config.verification.candidates
    best = result.verification.hypotheses[0]
    assert result.pose_estimator in best.estimators
    summary = json.loads(json.dumps(result.to_dict(), allow_nan=False))
    assert summary["success"] is True and 0.0 <= summary["confidence"] <= 1.0
    assert summary["config"]["estimator"] == "auto"


@pytest.fixture(scope="module")
def bunny_000_180(shared_data):
    return bunny_pair(shared_data, "bun000", "bun180")


@pytest.mark.parametrize("refine", [None, "point_to_plane"])
def test_a_pose_on_far_apart_real_scans_is_flagged_truthfully(registrar, bunny_000_180, refine):
    """bun000 -> bun180 (a half turn, little overlap): whatever the model finds, a wrong pose is
    not called a success, and a pose called a success is right (the flag's one job).

    Before the flag existed this pair returned a pose 157 deg wrong with nothing to tell.
    """
    source, target, truth = bunny_000_180
    result = registrar.register(source, target, refine=refine)
    right = rotation_error_deg(result.rotation, truth[:3, :3]) < 5.0
    assert result.success <= right, f"flagged a success at a wrong pose (confidence {result.confidence:.3f})"
    assert result.success == (result.confidence >= result.config.verification.success_threshold)
    assert (result.reason is None) == result.success


@pytest.mark.parametrize(("source_name", "target_name"), [("bun000", "bun315"), ("bun315", "chin")])
def test_a_right_pose_on_real_scans_is_a_success(registrar, shared_data, source_name, target_name):
    """Two real scan pairs (45 and 56 degrees apart, 70 and 57 % overlap) with ICP: the verified
    pose refines to the truth and is flagged a success."""
    source, target, truth = bunny_pair(shared_data, source_name, target_name)
    result = registrar.register(source, target, refine="point_to_plane")
    assert rotation_error_deg(result.rotation, truth[:3, :3]) < 1.0
    assert result.success


def test_an_initial_guess_joins_the_candidates(registrar, demo_pair):
    truth = demo_pair.true_transformation
    result = registrar.register(demo_pair.source, demo_pair.target, init=truth)
    names = [name for h in result.verification.hypotheses for name in h.estimators]
    assert "init" in names
    with pytest.raises(ValueError, match="init"):
        registrar.register(demo_pair.source, demo_pair.target, init=np.eye(3))


# ----------------------------------------------------------------------------- configuration
def test_runtime_config_round_trips_and_merges_partial_dicts():
    config = RuntimeConfig()
    assert RuntimeConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    changed = RuntimeConfig.from_dict({"fsr": {"iterations": 9}, "refinement": {"method": "point_to_point"}})
    assert changed.fsr == dataclasses.replace(FsrConfig(), iterations=9)
    assert changed.refinement == RefinementConfig(method="point_to_point")
    with pytest.raises(ValueError, match="unknown keys"):
        RuntimeConfig.from_dict({"fsr": {"tau": 0.1}})
    with pytest.raises(ValueError, match="unknown keys"):
        RuntimeConfig.from_dict({"icp": {}})
    with pytest.raises(ValueError, match="estimator"):
        RuntimeConfig(estimator="magic")
    with pytest.raises(ValueError, match="RefinementConfig.coarse_source_points"):
        RefinementConfig(coarse_source_points=5)
    with pytest.raises(ValueError, match="resolve"):  # verification None: the model's, unknown here
        config.with_seed(7)
    seeded = dataclasses.replace(config, verification=VerificationConfig()).with_seed(7)
    assert seeded.fsr.seed == seeded.ransac.seed == seeded.verification.seed == seeded.refinement.seed == 7


def _model_copy(tmp_path, runtime: dict):
    """The bundled model's files in ``tmp_path`` with ``runtime`` as its manifest's defaults."""
    import shutil

    from logdesc_rt.network import bundled_model_dir

    folder = tmp_path / "model"
    shutil.copytree(bundled_model_dir(), folder)
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["runtime"] = runtime
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def _model_without(tmp_path, *keys: str) -> tuple:
    """The bundled model's files in ``tmp_path`` with ``keys`` removed from its manifest's
    verification settings (a manifest stored before those settings existed), and the settings
    the bundled manifest stores. Every key must be there to remove."""
    from logdesc_rt.network import bundled_model_dir

    runtime = json.loads((bundled_model_dir() / "manifest.json").read_text())["runtime"]
    stored = dict(runtime["verification"])
    assert set(keys) <= set(stored), f"the bundled manifest lacks {set(keys) - set(stored)}"
    runtime["verification"] = {key: value for key, value in stored.items() if key not in keys}
    return _model_copy(tmp_path, runtime), stored


def test_the_models_runtime_defaults_come_from_its_manifest(tmp_path, demo_pair):
    """A model's manifest carries its runtime defaults (its success-flag calibration among
    them); a dict overrides them key by key, a RuntimeConfig keeps the model's verification."""
    # No exit model: the flag's threshold alone decides.
    model = _model_copy(tmp_path, {"verification": {"success_threshold": 0.999999, "exit_weights": []},
                                   "fsr": {"iterations": 7}})
    registrar = Registrar(model)
    assert registrar.config.verification.success_threshold == 0.999999
    assert registrar.config.fsr.iterations == 7
    result = registrar.register(demo_pair.source, demo_pair.target)
    assert result.config.verification.success_threshold == 0.999999
    assert result.confidence < 0.999999 and not result.success  # the manifest's threshold decided

    partial = Registrar(model, config={"fsr": {"iterations": 9}})
    assert partial.config.fsr.iterations == 9
    assert partial.config.verification.success_threshold == 0.999999  # kept from the manifest
    whole = Registrar(model, config=RuntimeConfig())
    assert whole.config.fsr.iterations == FsrConfig().iterations  # taken as given
    assert whole.config.verification.success_threshold == 0.999999  # None: the model's
    assert registrar.call_config({"estimator": "svd"}).verification.success_threshold == 0.999999

    bundled = Registrar()
    assert bundled.config.verification == RuntimeConfig.from_dict(bundled.manifest.runtime).verification


def test_a_bad_runtime_section_in_a_manifest_fails_when_the_model_is_read(tmp_path):
    from logdesc_rt.errors import ModelFileError

    with pytest.raises(ModelFileError, match="unknown keys"):
        Registrar(_model_copy(tmp_path, {"verification": {"threshold": 0.5}}))


def test_pair_matches_reads_the_prepared_pair_without_copies(registrar, demo_pair):
    pair = registrar.match(demo_pair.source, demo_pair.target)
    fields = {field.name for field in dataclasses.fields(pair)}
    assert not fields & {"source_points", "source_index", "source_network", "normalization"}
    assert pair.source_points is pair.prepared.source_points
    assert pair.target_network is pair.prepared.target_network
    assert pair.config == registrar.config
    np.testing.assert_array_equal(pair.pose("svd"), pair.pose("svd", config=registrar.config))


def test_registrar_and_call_configs_are_used_and_reported(demo_pair):
    config = RuntimeConfig.from_dict({"estimator": "ransac", "ransac": {"max_iterations": 500}})
    registrar = Registrar(config=config, max_points=512)
    assert registrar.config.subsampling.max_points == 512 == registrar.max_points
    assert registrar.config.matching == registrar.manifest.matching  # the model's, resolved
    result = registrar.register(demo_pair.source, demo_pair.target, seed=4, refine="point_to_plane")
    assert result.pose_estimator == "ransac" and result.refinement == "point_to_plane"
    assert result.config.ransac.max_iterations == 500 and result.config.ransac.seed == 4
    assert result.subsampled and result.source_points_used == 512
    # A per-call config replaces the Registrar's; keyword arguments still win over it.
    call = registrar.register(
        demo_pair.source, demo_pair.target, config=RuntimeConfig(), estimator="svd", refine=None
    )
    working_size = registrar.manifest.points_per_cloud  # a whole RuntimeConfig: the model's working size
    assert call.pose_estimator == "svd" and call.config.subsampling.max_points == working_size
    assert call.source_points_used == min(len(demo_pair.source), working_size)
    with pytest.raises(ValueError, match="estimator"):
        registrar.register(demo_pair.source, demo_pair.target, estimator="magic")


def test_a_fitted_calibration_written_into_a_manifest_is_the_models_flag(tmp_path):
    """benchmarks/calibrate_success.py --manifest: the fit lands where the runtime reads it."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import calibrate_success

    model = _model_copy(tmp_path, {"fsr": {"iterations": 7}})
    fitted = dataclasses.replace(
        VerificationConfig(), weights=tuple(0.1 * i for i in range(len(VERIFICATION_FEATURES))), bias=-1.5,
        success_threshold=0.6,
    )
    calibrate_success.write_calibration(model, fitted)
    config = Registrar(model).config
    assert config.verification == fitted
    assert config.fsr.iterations == 7  # the rest of the manifest's runtime section is kept


def test_settings_a_calibration_was_fitted_with_are_stored_with_it(tmp_path):
    """fit --set source_points=1000 ...: a flag fitted on capped verification must run capped."""
    calibrate_success = _calibrate_success()
    model = _model_copy(tmp_path, {})
    defaults = VerificationConfig()
    fitted = dataclasses.replace(defaults, source_points=defaults.source_points // 2,
                                 target_points=defaults.target_points // 2, turn_over_axes=4)
    calibrate_success.write_calibration(model, fitted, {"source_points": 1, "target_points": 1})
    verification = Registrar(model).config.verification
    assert (verification.source_points, verification.target_points) == (fitted.source_points, fitted.target_points)
    assert verification == fitted


def _calibrate_success():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import calibrate_success

    return calibrate_success


def test_the_calibrations_resampled_group_is_new_pairs_and_leaves_the_others_seeds(shared_data):
    """A group's number seeds its pairs: the resampled group is appended, so the four older
    groups (and the near-truth candidates) keep their pairs, and its clouds are resampled ones."""
    calibrate_success = _calibrate_success()
    groups = calibrate_success.GROUPS
    assert groups[:4] == ("val_in_range", "val_any_rotation", "val_small_overlap", "bunny_unbenchmarked")
    assert calibrate_success.INIT_GROUP_NUMBER == 4
    (_, partial_source, _, _), = calibrate_success.synthetic_pairs("val_in_range", 1)
    (name, source, target, truth), = calibrate_success.synthetic_pairs("val_resampled_partial", 1)
    assert name == "val_resampled_partial/0000"
    # Half the shape's samples per cloud, then the crop: fewer points than the paper's 768.
    assert len(source) < len(partial_source) == 768
    # The truth holds: the moved source lies near the target's points (noise 0.01, clipped 0.05).
    moved = source @ truth[:3, :3].T + truth[:3, 3]
    distance = np.linalg.norm(moved[:, None, :] - target[None, :, :], axis=2).min(axis=1)
    assert np.median(distance) < 0.1


def test_count_reads_the_chosen_hypothesis_of_each_pair():
    """calibrate_success.group_counts: the calibration chooses each pair's most confident
    hypothesis; its verified / unrefined rightness and claim are counted per group and per
    scan class, and "any_right" counts a right hypothesis that was not chosen."""
    calibrate_success = _calibrate_success()
    config = VerificationConfig(weights=(1.0,) + (0.0,) * 9, bias=0.0, success_threshold=0.6)

    def row(pair, fitness, verified, unrefined, within=True):
        features = [fitness] + [0.0] * 9
        return {"pair": pair, "group": pair.split("/")[0], "features": features, "verified_right": verified,
                "unrefined_right": unrefined, "unrefined_claimable": within}

    rows = {
        # chosen: the first (fitness 2, confidence 0.88), right and claimed
        "val_scan/0000": [row("val_scan/0000", 2.0, True, True), row("val_scan/0000", 0.1, False, False)],
        # chosen: a wrong one; a right one exists below it
        "val_scan/0001": [row("val_scan/0001", 1.0, False, False), row("val_scan/0001", 0.5, True, True)],
        # chosen: right verified, the unrefined pose right but astray (not claimed without ICP)
        "val_in_range/0000": [row("val_in_range/0000", 3.0, True, True, within=False)],
        "val_in_range/0001": [],  # too few matches: no hypothesis, not counted
    }
    counts = calibrate_success.group_counts(rows, config, {"val_scan/0000": "bench", "val_scan/0001": "bench"})
    assert counts["val_scan"] == {"pairs": 2, "verified_right": 1, "unrefined_right": 1, "claimed": 2,
                                  "right_among_claimed": 1, "any_right": 2}
    assert counts["val_scan:bench"] == counts["val_scan"]
    assert counts["val_in_range"] == {"pairs": 1, "verified_right": 1, "unrefined_right": 1, "claimed": 0,
                                      "right_among_claimed": 0, "any_right": 1}


def test_collect_refuses_a_cache_of_another_model(tmp_path):
    """The matches of two models never mix in one calibration cache."""
    calibrate_success = _calibrate_success()
    (tmp_path / calibrate_success.MODEL_RECORD).write_text(json.dumps({"id": "another", "description": "x"}))
    with pytest.raises(SystemExit, match="another model"):
        calibrate_success.collect(["val_in_range"], 1, 1, cache=tmp_path)
    assert not (tmp_path / "val_in_range").exists()


def test_code_defaults_are_the_shipped_models_matching_and_calibration():
    """``MatchingConfig()`` and ``VerificationConfig()`` are what the bundled model runs with, so
    a reader of the defaults learns what ships; matching stored before the dustbin option (v3
    and older) keeps the paper's reading."""
    from logdesc_rt.config import MatchingConfig

    bundled = Registrar()
    assert VerificationConfig() == RuntimeConfig.from_dict(bundled.manifest.runtime).verification
    assert MatchingConfig() == bundled.manifest.matching
    legacy = {"sinkhorn_iterations": 50, "match_threshold": 0.0}
    assert MatchingConfig.from_stored(legacy).dustbin_in_mutual_test is True
    assert MatchingConfig.from_stored({**legacy, "dustbin_in_mutual_test": False}) == MatchingConfig()


def test_a_calibration_stored_without_its_candidates_keeps_the_four_of_its_day(tmp_path):
    """v3's manifest holds weights and a threshold but no candidate set: it was fitted with
    four estimators, and its ``agreement`` feature counts among them, so "core" (added later,
    in today's default set) must not join its candidates."""
    from logdesc_rt.network import LEGACY_CANDIDATES

    model, _ = _model_without(tmp_path, "candidates")
    assert Registrar(model).config.verification.candidates == LEGACY_CANDIDATES
    assert "core" in VerificationConfig().candidates  # today's default set differs


# --- The second look (logdesc_rt/verification.py docstring) ---------------------------------


def _rigid(rotvec, translation) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    pose[:3, 3] = translation
    return pose


def _plate_with_a_ridge(rng: np.random.Generator) -> np.ndarray:
    """(N, 3) a 2 x 1 plate, one face only (a scan sees one side), gently rippled, with a ridge
    near one end: turned over about any in-plane axis, the plate fits itself again roughly, the
    ridge does not; the ripples let the ICP find the turn about the plate's normal."""
    x, y = rng.uniform(-1, 1, 3000), rng.uniform(-0.5, 0.5, 3000)
    plate = np.column_stack([x, y, 0.04 * np.sin(4.0 * x) * np.cos(5.0 * y)])
    ridge = np.column_stack([rng.uniform(0.4, 0.8, 600), rng.uniform(-0.1, 0.3, 600), rng.uniform(0.0, 0.25, 600)])
    return np.vstack([plate, ridge]) + rng.normal(scale=0.003, size=(3600, 3))


@pytest.mark.parametrize("axis_deg", [20.0, 65.0, 140.0])
def test_the_second_look_turns_a_flipped_plate_back(axis_deg):
    """The only candidate is the plate turned over about an in-plane axis (the failure of
    symmetric scans: every estimator finds the flip). The second look's turned-over hypothesis
    finds the truth and ranks first; without it the flip stays."""
    rng = np.random.default_rng(3)
    source = _plate_with_a_ridge(rng)
    truth = _rigid([0.3, -0.5, 0.9], [0.4, -0.2, 0.1])
    target = source @ truth[:3, :3].T + truth[:3, 3] + rng.normal(scale=0.003, size=source.shape)
    axis = np.array([np.cos(np.radians(axis_deg)), np.sin(np.radians(axis_deg)), 0.0])
    centre = source.mean(axis=0)
    flip = np.eye(4)
    flip[:3, :3] = Rotation.from_rotvec(np.pi * axis).as_matrix()
    flip[:3, 3] = centre - flip[:3, :3] @ centre
    flipped = truth @ flip
    matched = source[:50]
    arguments = (source, target, matched, matched @ truth[:3, :3].T + truth[:3, 3], np.full(50, 0.5), 1.0)

    with_look = PoseVerifier(*arguments).verify([("fsr", flipped)])
    best = with_look.best
    assert best.estimators[0] == "turned_over"
    assert rotation_error_deg(best.verified_transformation[:3, :3], truth[:3, :3]) < 1.0
    # Its own pose is the refined one: a raw half-turn is no estimate.
    assert np.array_equal(best.transformation, best.verified_transformation)

    without = PoseVerifier(*arguments, VerificationConfig(turn_over_axes=0, second_consensus=())).verify(
        [("fsr", flipped)]
    )
    assert [h.estimators for h in without.hypotheses] == [("fsr",)]
    assert rotation_error_deg(without.best.verified_transformation[:3, :3], truth[:3, :3]) > 170.0


def test_the_second_looks_spin_turns_a_plate_back_end_to_end():
    """The only candidate, and every match, is the plate spun half a turn in its own plane (a
    tub or a table seen from the wrong end): no turn-over (axes in the plane) and no ICP reaches
    the truth from there. With ``turn_over_spin`` the spun hypothesis finds it and ranks first;
    without, the spin stays."""
    rng = np.random.default_rng(4)
    # A 2 x 1 plate whose ripples look the same spun half a turn (only the ridge near one end
    # tells the ends apart), so that the spun start lies in the ICP's basin of the truth.
    x, y = rng.uniform(-1, 1, 3000), rng.uniform(-0.5, 0.5, 3000)
    plate = np.column_stack([x, y, 0.04 * np.cos(4.0 * x) * np.cos(5.0 * y)])
    ridge = np.column_stack([rng.uniform(0.4, 0.8, 600), rng.uniform(-0.1, 0.3, 600), rng.uniform(0.0, 0.25, 600)])
    source = np.vstack([plate, ridge]) + rng.normal(scale=0.003, size=(3600, 3))
    truth = _rigid([0.3, -0.5, 0.9], [0.4, -0.2, 0.1])
    target = source @ truth[:3, :3].T + truth[:3, 3] + rng.normal(scale=0.003, size=source.shape)
    centre = source.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((source - centre).T))
    spin = np.eye(4)
    spin[:3, :3] = Rotation.from_rotvec(np.pi * axes[:, 0]).as_matrix()  # about the plate's normal
    spin[:3, 3] = centre - spin[:3, :3] @ centre
    spun = truth @ spin
    matched = source[:50]
    arguments = (source, target, matched, matched @ spun[:3, :3].T + spun[:3, 3], np.full(50, 0.5), 1.0)

    with_spin = PoseVerifier(*arguments, VerificationConfig(turn_over_spin=True)).verify([("fsr", spun)])
    best = with_spin.best
    assert best.estimators[0] == "spun"
    assert rotation_error_deg(best.verified_transformation[:3, :3], truth[:3, :3]) < 1.0
    assert np.array_equal(best.transformation, best.verified_transformation)

    without = PoseVerifier(*arguments, VerificationConfig(turn_over_spin=False)).verify([("fsr", spun)])
    assert all(rotation_error_deg(h.verified_transformation[:3, :3], truth[:3, :3]) > 170.0 for h in without.hypotheses)


def test_the_second_consensus_finds_the_pose_the_outvoted_matches_agree_on():
    """60 % of the matches agree on a wrong pose, 40 % on the true one: every estimator reads
    the wrong one; without the matches it explains, RANSAC finds the true one."""
    rng = np.random.default_rng(8)
    points = rng.uniform(-1, 1, size=(300, 3))
    truth, wrong = _rigid([0.2, 0.1, -0.3], [0.1, 0.0, 0.2]), _rigid([2.0, -1.0, 0.5], [-0.3, 0.2, 0.0])
    target = np.vstack([points[:180] @ wrong[:3, :3].T + wrong[:3, 3], points[180:] @ truth[:3, :3].T + truth[:3, 3]])
    confidences = np.full(300, 0.5)
    first = dict(candidate_poses(points, target, confidences))
    assert rotation_error_deg(first["ransac"][:3, :3], wrong[:3, :3]) < 1e-3
    second = dict(
        unexplained_candidate_poses(points, target, confidences, first["ransac"], 0.08, estimators=("ransac",))
    )
    assert set(second) == {"ransac"}
    assert rotation_error_deg(second["ransac"][:3, :3], truth[:3, :3]) < 1e-3
    # A pose that explains all but two matches leaves nothing to fit.
    almost = target.copy()
    almost[180:298] = points[180:298] @ wrong[:3, :3].T + wrong[:3, 3]
    assert unexplained_candidate_poses(points, almost, confidences, wrong, 0.08) == []


def test_the_runtime_second_look_is_the_configs(registrar, demo_pair):
    """register() scores the second look's hypotheses as the calibration did, and the config
    turns each part off."""
    full = registrar.register(demo_pair.source, demo_pair.target, thorough=True)
    names = {name for h in full.verification.hypotheses for name in h.estimators}
    assert "turned_over" in names
    off = registrar.register(
        demo_pair.source, demo_pair.target, config={"verification": {"turn_over_axes": 0, "second_consensus": []}},
        thorough=True,
    )
    names = {name for h in off.verification.hypotheses for name in h.estimators}
    assert "turned_over" not in names and not any(name.startswith("unexplained_") for name in names)
    assert rotation_error_deg(full.rotation, demo_pair.true_transformation[:3, :3]) < 2.0


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"turn_over_axes": -1}, "turn_over_axes"),
        ({"turn_over_axes": 2.5}, "turn_over_axes"),
        ({"turn_over_axes": True}, "turn_over_axes"),
        ({"second_consensus": "ransac"}, "second_consensus"),
        ({"second_consensus": True}, "second_consensus"),
        ({"second_consensus": ["magic"]}, "second_consensus"),
        ({"descriptor_consensus": "ransac"}, "descriptor_consensus"),
        ({"descriptor_consensus": ["descriptor_ransac"]}, "descriptor_consensus"),
        ({"refit_spacings": -1.0}, "refit_spacings"),
        ({"refit_spacings": float("nan")}, "refit_spacings"),
        ({"refit_spacings": float("inf")}, "refit_spacings"),
        ({"refit_plane_steps": -1}, "refit_plane_steps"),
        ({"refit_plane_steps": 1.5}, "refit_plane_steps"),
        ({"refit_plane_steps": True}, "refit_plane_steps"),
        ({"refit_point_weight": -0.1}, "refit_point_weight"),
        ({"refit_point_weight": float("nan")}, "refit_point_weight"),
        ({"turn_over_spin": 1}, "turn_over_spin"),
        ({"verified_fallback_rmse": -0.1}, "verified_fallback_rmse"),
        ({"verified_fallback_rmse": float("nan")}, "verified_fallback_rmse"),
    ],
)
def test_bad_second_look_settings_are_named(values, message):
    with pytest.raises(ValueError, match=message):
        VerificationConfig(**values)


def test_a_calibration_stored_before_the_second_look_runs_without_it(tmp_path):
    """A manifest calibrated without the second look holds no second-look settings: its flag was
    fitted without turn-overs as rivals, so the model runs without the second look; the shipped
    manifest stores its own settings."""
    model, stored = _model_without(
        tmp_path, "turn_over_axes", "second_consensus", "descriptor_consensus", "refit_spacings"
    )
    assert stored["turn_over_axes"] == 6
    verification = Registrar(model).config.verification
    assert verification.turn_over_axes == 0 and verification.second_consensus == ()
    assert verification.descriptor_consensus == () and verification.refit_spacings == 0.0
    assert Registrar().config.verification.second_consensus == ("ransac",)


def test_a_calibration_stored_before_the_descriptor_candidates_runs_without_them(tmp_path):
    """A manifest fitted with the second look but before the descriptors' candidates keeps the
    second look and leaves the descriptors' candidates out (its ``agreement`` never counted them)."""
    model, _ = _model_without(tmp_path, "descriptor_consensus")
    verification = Registrar(model).config.verification
    assert verification.turn_over_axes == 6 and verification.descriptor_consensus == ()


def test_a_calibration_stored_before_the_coarse_refit_returns_the_estimators_pose(tmp_path):
    """A manifest without ``refit_spacings`` returns the estimator's own pose without ICP (as
    when it was fitted) and keeps every other setting; the shipped manifest stores its own."""
    model, stored = _model_without(tmp_path, "refit_spacings")
    assert stored["refit_spacings"] > 0
    verification = Registrar(model).config.verification
    assert verification.refit_spacings == 0.0 and verification.descriptor_consensus == ("ransac",)


def test_a_calibration_stored_before_the_verified_fallback_runs_without_it(tmp_path):
    """A manifest without ``verified_fallback_rmse`` (fitted when a straying re-fit was never
    replaced) runs without the fallback and keeps every other setting; the shipped manifest
    stores its own."""
    model, stored = _model_without(tmp_path, "verified_fallback_rmse")
    assert stored["verified_fallback_rmse"] == 0.5
    verification = Registrar(model).config.verification
    assert verification.verified_fallback_rmse == 0.0 and verification.refit_plane_steps == 3


def test_a_calibration_stored_before_the_plane_steps_returns_the_plain_refit(tmp_path, demo_pair):
    """A manifest without ``refit_plane_steps`` (calibrated before the plane steps existed) returns the SVD re-fit
    without ICP, as when its numbers were measured; the shipped manifest stores 3 steps, and
    its pose without ICP differs from the plain re-fit's."""
    model, stored = _model_without(tmp_path, "refit_plane_steps")
    assert stored["refit_plane_steps"] == 3
    legacy = Registrar(model)
    assert legacy.config.verification.refit_plane_steps == 0 and legacy.config.verification.refit_spacings == 2.0
    shipped = Registrar()
    assert shipped.config.verification.refit_plane_steps == 3
    plain = legacy.register(demo_pair.source, demo_pair.target, refine=None).transformation
    with_steps = shipped.register(demo_pair.source, demo_pair.target, refine=None).transformation
    assert not np.array_equal(plain, with_steps)


def test_mutual_nearest_descriptors_keep_only_mutual_best_pairs():
    """Source 0 and 1 both like target 0 best; only the mutual one (1 -> 0) is kept, 2 <-> 2 too;
    the similarity is the confidence, clipped at 0."""
    source = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]], dtype=np.float32)
    target = np.array([[0.6, 0.8, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]], dtype=np.float32)
    matches = mutual_nearest_descriptors(source, target)
    assert matches.source_index.tolist() == [1, 2] and matches.target_index.tolist() == [0, 2]
    np.testing.assert_allclose(matches.confidence, [0.8, 1.0], rtol=1e-6)
    opposite = mutual_nearest_descriptors(source[:1], -source[:1])
    assert opposite.confidence.tolist() == [0.0]


def test_descriptor_candidates_read_the_descriptors_own_matches():
    """Descriptor matches that hold the truth give a ``descriptor_ransac`` candidate at the
    truth, whatever the matcher's matches say; fewer than three give none."""
    from logdesc_rt.matching import Matches

    rng = np.random.default_rng(3)
    source = rng.uniform(-1, 1, size=(200, 3))
    truth = _rigid([0.3, -0.2, 0.9], [0.1, 0.2, 0.0])
    target = source @ truth[:3, :3].T + truth[:3, 3]
    order = rng.permutation(200)
    right = np.arange(120)
    wrong = np.arange(120, 200)
    matches = Matches(
        np.concatenate([right, wrong]), np.concatenate([right, order[wrong]]), np.full(200, 0.5)
    )
    candidates = dict(descriptor_candidate_poses(source, target, matches, estimators=("ransac", "svd")))
    assert set(candidates) == {"descriptor_ransac", "descriptor_svd"}
    assert rotation_error_deg(candidates["descriptor_ransac"][:3, :3], truth[:3, :3]) < 1e-3
    few = Matches(right[:2], right[:2], np.full(2, 0.5))
    assert descriptor_candidate_poses(source, target, few) == []


def test_the_runtime_scores_the_descriptor_candidates_when_configured(registrar, demo_pair):
    """register() verifies ``descriptor_ransac`` when the config asks, and not otherwise."""
    def names(result):
        return {name for h in result.verification.hypotheses for name in h.estimators}

    on = registrar.register(
        demo_pair.source, demo_pair.target, config={"verification": {"descriptor_consensus": ["ransac"]}},
        thorough=True,
    )
    off = registrar.register(
        demo_pair.source, demo_pair.target, config={"verification": {"descriptor_consensus": []}}, thorough=True
    )
    assert "descriptor_ransac" in names(on) and not any(name.startswith("descriptor_") for name in names(off))


def _coarse_hypothesis(estimator_pose: np.ndarray, verified_pose: np.ndarray):
    from logdesc_rt.verification import Hypothesis

    return Hypothesis(("fsr",), estimator_pose, verified_pose, {}, 0.9, True)


def _refit(spacings: float, plane_steps: int = 0):
    """A verification config that re-fits within ``spacings`` (and ``plane_steps`` plane steps)."""
    from logdesc_rt.config import VerificationConfig

    return VerificationConfig(refit_spacings=spacings, refit_plane_steps=plane_steps)


def test_coarse_pose_refits_the_matches_the_verified_pose_explains():
    """Matches: 150 noisy right ones and 100 wrong. From an estimator's pose 4 degrees off and a
    verified pose 1 degree off, the re-fit lands closer to the truth than either (a least-squares
    fit of the right matches alone); with 0 spacings it is the estimator's pose, and a verified
    pose that explains fewer than three matches leaves the estimator's pose too."""
    from logdesc_rt.pose_selection import coarse_pose

    rng = np.random.default_rng(5)
    target_working = rng.uniform(-1, 1, size=(800, 3))
    truth = _rigid([0.2, 0.5, -0.3], [0.3, -0.1, 0.2])
    source_matched = rng.uniform(-1, 1, size=(250, 3))
    target_matched = source_matched @ truth[:3, :3].T + truth[:3, 3]
    target_matched[:150] += rng.normal(scale=0.005, size=(150, 3))
    target_matched[150:] = rng.uniform(-1, 1, size=(100, 3))
    confidences = rng.uniform(0.2, 1.0, size=250)
    centre = source_matched[:150].mean(axis=0)
    estimator_pose, verified_pose = _turned(truth, 4.0, centre), _turned(truth, 1.0, centre)

    refit = coarse_pose(
        _coarse_hypothesis(estimator_pose, verified_pose), source_matched, target_matched, confidences,
        target_working, _refit(2.0),
    )
    error = rotation_error_deg(refit[:3, :3], truth[:3, :3])
    assert error < 0.3 and np.linalg.norm(refit[:3, 3] - truth[:3, 3]) < 0.01
    assert error < rotation_error_deg(verified_pose[:3, :3], truth[:3, :3])

    hypothesis = _coarse_hypothesis(estimator_pose, verified_pose)
    kept = coarse_pose(hypothesis, source_matched, target_matched, confidences, target_working, _refit(0.0))
    assert kept is hypothesis.transformation
    elsewhere = truth.copy()
    elsewhere[0, 3] += 5.0  # two radii away: no match within two spacings
    far = _coarse_hypothesis(estimator_pose, elsewhere)
    alone = coarse_pose(far, source_matched[:150], target_matched[:150], confidences[:150], target_working, _refit(2.0))
    assert alone is far.transformation
    # Inliers all on one line fix no rotation about it: the estimator's pose, not a guess.
    line = np.outer(np.linspace(-1.0, 1.0, 50), [1.0, 0.2, -0.3])
    on_line = line @ truth[:3, :3].T + truth[:3, 3]
    straight = coarse_pose(hypothesis, line, on_line, np.full(50, 0.5), target_working, _refit(2.0))
    assert straight is hypothesis.transformation


def test_coarse_pose_plane_steps_discount_matches_that_slide_along_the_surface():
    """Two scans sample a surface independently: a learned match pairs a point with a neighbour
    of its twin. Here every twin sits 0.02 along a curved surface from its match, all turning
    the same way about one axis (the worst case: the slides add up to a rotation). The SVD
    re-fit takes the slide for motion (about 1.5 degrees off); the point-to-plane steps, whose
    residuals ignore motion along the surface, land within half of that (0.5). No steps: the SVD
    re-fit exactly."""
    from logdesc_rt.pose_selection import coarse_pose

    def surface(x, y):
        return 0.5 * np.sin(3.0 * x) * np.cos(3.0 * y)

    rng = np.random.default_rng(3)
    x, y = rng.uniform(-1, 1, 5000), rng.uniform(-1, 1, 5000)
    target_working = np.column_stack([x, y, surface(x, y)])
    truth = _rigid([0.4, -0.2, 0.7], [0.5, -2.0, 1.0])
    target_matched = target_working[rng.choice(len(target_working), 300, replace=False)]
    around = np.column_stack([-target_matched[:, 1], target_matched[:, 0]])
    slid = target_matched[:, :2] + 0.02 * around / np.linalg.norm(around, axis=1, keepdims=True)
    twins = np.column_stack([slid, surface(slid[:, 0], slid[:, 1])])
    source_matched = (twins - truth[:3, 3]) @ truth[:3, :3]  # truth maps each source point to its twin
    confidences = rng.uniform(0.3, 1.0, size=300)
    hypothesis = _coarse_hypothesis(truth, truth)

    def error(plane_steps: int) -> float:
        from logdesc_rt.config import VerificationConfig

        pose = coarse_pose(
            hypothesis, source_matched, target_matched, confidences, target_working,
            VerificationConfig(refit_spacings=2.0, refit_plane_steps=plane_steps, refit_point_weight=0.1),
        )
        return rotation_error_deg(pose[:3, :3], truth[:3, :3])

    least_squares, plane = error(0), error(3)
    assert least_squares > 1.0 and plane < least_squares / 2
    assert error(0) == rotation_error_deg(
        coarse_pose(hypothesis, source_matched, target_matched, confidences, target_working, _refit(2.0))[:3, :3],
        truth[:3, :3],
    )


def test_coarse_pose_plane_steps_follow_the_clouds_frame():
    """The plane steps linearise about the matches' centroid: the same pair 1e5 away and in
    millimetres re-fits to the same pose (mapped back)."""
    from logdesc_rt.config import VerificationConfig
    from logdesc_rt.pose_selection import coarse_pose

    rng = np.random.default_rng(8)
    x, y = rng.uniform(-1, 1, 3000), rng.uniform(-1, 1, 3000)
    target_working = np.column_stack([x, y, 0.4 * np.sin(3.0 * x) * np.cos(2.0 * y)])
    truth = _rigid([0.1, 0.3, -0.2], [0.2, 0.1, -0.1])
    target_matched = target_working[rng.choice(3000, 200, replace=False)]
    source_matched = (target_matched + rng.normal(scale=0.01, size=(200, 3)) - truth[:3, 3]) @ truth[:3, :3]
    confidences = rng.uniform(0.3, 1.0, size=200)
    config = VerificationConfig(refit_plane_steps=3)
    here = coarse_pose(
        _coarse_hypothesis(truth, truth), source_matched, target_matched, confidences, target_working, config
    )
    shift, scale = np.array([1e5, -2e5, 3e4]), 1000.0
    moved_truth = truth.copy()
    moved_truth[:3, 3] = scale * truth[:3, 3] + shift - truth[:3, :3] @ shift
    there = coarse_pose(
        _coarse_hypothesis(moved_truth, moved_truth), scale * source_matched + shift, scale * target_matched + shift,
        confidences, scale * target_working + shift, config,
    )
    assert rotation_error_deg(there[:3, :3], here[:3, :3]) < 1e-6
    back = there[:3, 3] - shift + there[:3, :3] @ shift
    assert np.allclose(back / scale, here[:3, 3], atol=1e-8)


def test_register_without_icp_returns_the_coarse_pose_of_its_chosen_hypothesis(registrar, demo_pair):
    """register(refine=None) returns coarse_pose of the hypothesis it chose (the estimator's own
    pose with refit_spacings=0); ICP starts from the verified pose either way."""
    from logdesc_rt.pose_selection import coarse_pose

    pair = registrar.match(demo_pair.source, demo_pair.target)
    result = registrar.register_matches(pair, refine=None)
    chosen = result.verification.best
    c = pair.correspondences
    expected = coarse_pose(
        chosen, pair.source_points[c[:, 0]], pair.target_points[c[:, 1]], pair.matches.confidence,
        pair.target_points[pair.target_index], registrar.config.verification,
    )
    assert np.array_equal(result.transformation, expected)
    assert not np.array_equal(expected, chosen.transformation)  # the refit moved it
    assert rotation_error_deg(expected[:3, :3], demo_pair.true_transformation[:3, :3]) < 2.0
    own = Registrar(config={"verification": {"refit_spacings": 0.0}}).register(
        demo_pair.source, demo_pair.target, refine=None
    )
    assert np.array_equal(own.transformation, own.verification.best.transformation)


def test_a_straying_refit_gives_way_to_the_verified_pose_only_where_the_clouds_coincide():
    """pose_without_icp: the re-fit within same_pose_deg of the verified pose is returned and
    claimable; a straying one gives way to the verified pose when the hypothesis' rmse_ratio is
    below verified_fallback_rmse, else it is returned unclaimable."""
    from logdesc_rt.pose_selection import pose_without_icp
    from logdesc_rt.verification import Hypothesis

    verified, refit = _rigid([0.0, 0.0, 0.1], [0.0, 0.0, 0.0]), np.eye(4)

    def hypothesis(rmse_ratio: float) -> Hypothesis:
        return Hypothesis(("fsr",), np.eye(4), verified, {"rmse_ratio": rmse_ratio}, 0.9, True)

    on, off = VerificationConfig(verified_fallback_rmse=0.5), VerificationConfig(verified_fallback_rmse=0.0)
    pose, claimable = pose_without_icp(hypothesis(0.3), refit, True, on)
    assert pose is refit and claimable
    pose, claimable = pose_without_icp(hypothesis(0.3), refit, False, on)
    assert pose is verified and claimable
    pose, claimable = pose_without_icp(hypothesis(0.6), refit, False, on)
    assert pose is refit and not claimable
    pose, claimable = pose_without_icp(hypothesis(0.0), refit, False, off)
    assert pose is refit and not claimable


def test_register_returns_the_verified_pose_where_the_refit_strays_on_clouds_that_coincide(demo_pair):
    """With a same_pose_deg so small that every re-fit strays, register() without ICP returns
    the chosen hypothesis' verified pose, claimed, on the demo pair (dense clouds that coincide);
    without the fallback it returns the re-fit, unclaimed."""
    strict = {"verification": {"same_pose_deg": 1e-6}}
    fallback = Registrar(config=strict).register(demo_pair.source, demo_pair.target, refine=None)
    chosen = fallback.verification.best
    assert chosen.features["rmse_ratio"] < fallback.config.verification.verified_fallback_rmse
    assert np.array_equal(fallback.transformation, chosen.verified_transformation)
    assert fallback.success and fallback.confidence == chosen.confidence
    assert rotation_error_deg(fallback.transformation[:3, :3], demo_pair.true_transformation[:3, :3]) < 2.0
    strict["verification"]["verified_fallback_rmse"] = 0.0
    refit_only = Registrar(config=strict).register(demo_pair.source, demo_pair.target, refine=None)
    assert not np.array_equal(refit_only.transformation, chosen.verified_transformation)
    assert not refit_only.success and refit_only.confidence == 0.0
    assert "from the alignment verification found" in refit_only.reason


def test_the_held_out_flag_never_judges_a_pair_by_a_fit_on_its_own_shape(monkeypatch):
    """calibrate_success.cross_validated_outcomes: every pair is flagged once, by a calibration
    fitted without any pair of its shape (the scan group reuses shapes across pairs)."""
    from logdesc_rt.config import VerificationConfig

    calibrate_success = _calibrate_success()
    rng = np.random.default_rng(0)
    shapes, rows = {}, []
    for index in range(40):
        pair = f"val_scan/{index:04d}"
        shapes[pair] = f"shape_{index % 9}"  # several pairs per shape
        for _ in range(3):
            right = bool(rng.random() < 0.6)
            features = rng.normal(size=len(calibrate_success.FEATURES)) + (1.5 if right else 0.0)
            rows.append({"pair": pair, "group": "val_scan", "features": features.tolist(), "verified_right": right,
                         "unrefined_right": right, "unrefined_claimable": True, "estimators": ["fsr"], "refined": True})
    fitted_on: list[set[str]] = []
    real_calibrate = calibrate_success.calibrate

    def recording_calibrate(training_rows, base):
        fitted_on.append({row["pair"] for row in training_rows})
        return real_calibrate(training_rows, base)

    monkeypatch.setattr(calibrate_success, "calibrate", recording_calibrate)
    outcomes = calibrate_success.cross_validated_outcomes(rows, VerificationConfig(), shapes, folds=4)
    assert sorted(outcomes) == sorted(shapes) and len(fitted_on) == 4
    judged_by = {}
    for pairs in fitted_on:
        held_out_shapes = set(shapes.values()) - {shapes[p] for p in pairs}
        assert held_out_shapes  # each fit leaves some shapes out ...
        for pair in shapes:
            if shapes[pair] in held_out_shapes:
                judged_by.setdefault(pair, 0)
                judged_by[pair] += 1
    assert all(count == 1 for count in judged_by.values()) and len(judged_by) == len(shapes)  # ... each exactly once


# -- the fast exit --------------------------------------------------------------------------
def _exit_config(threshold: float) -> dict:
    """An exit model that trusts fitness alone (hand-set, for the tests): confidence 0.95 at a
    fitness of 1, 0.12 at 0."""
    from logdesc_rt.config import EXIT_FEATURES

    weights = [5.0 if name == "fitness" else 0.0 for name in EXIT_FEATURES]
    return {"verification": {"exit_weights": weights, "exit_bias": -2.0, "exit_threshold": threshold}}


def test_a_sure_pair_takes_the_fast_exit_and_an_unsure_one_gets_the_full_verification(registrar, demo_pair):
    """Exit: one hypothesis, the exit estimator's, with the exit model's confidence, and a
    right pose; no exit: exactly the result without an exit model (same pose, hypotheses,
    confidence), so the full path is unchanged by the attempt."""
    from logdesc_rt.metrics import rotation_error_deg

    full = registrar.register(demo_pair.source, demo_pair.target, thorough=True)
    assert not full.verification.fast_exit and len(full.verification.hypotheses) > 1

    fast = registrar.register(demo_pair.source, demo_pair.target, config=_exit_config(0.8))
    assert fast.verification.fast_exit
    assert fast.verification.candidate_count == 1 and fast.pose_estimator == "fsr"
    best = fast.verification.best
    expected = 1.0 / (1.0 + np.exp(2.0 - 5.0 * best.features["fitness"]))
    assert fast.confidence == pytest.approx(expected) and fast.success
    assert rotation_error_deg(fast.rotation, demo_pair.true_transformation[:3, :3]) < 2.0
    again = registrar.register(demo_pair.source, demo_pair.target, config=_exit_config(0.8))
    assert np.array_equal(again.transformation, fast.transformation)  # same input, same output

    unsure = registrar.register(demo_pair.source, demo_pair.target, config=_exit_config(0.99))
    assert not unsure.verification.fast_exit
    assert np.array_equal(unsure.transformation, full.transformation)
    assert unsure.confidence == full.confidence
    assert [h.estimators for h in unsure.verification.hypotheses] == [
        h.estimators for h in full.verification.hypotheses
    ]


def test_the_fast_exit_is_skipped_for_a_chosen_estimator_or_an_initial_guess(registrar, demo_pair):
    config = _exit_config(0.5)
    chosen = registrar.register(demo_pair.source, demo_pair.target, config=config, estimator="svd")
    assert not chosen.verification.fast_exit
    init = registrar.register(demo_pair.source, demo_pair.target).transformation
    assert not registrar.register(demo_pair.source, demo_pair.target, config=config, init=init).verification.fast_exit


def test_an_exit_model_must_have_one_weight_per_exit_feature():
    with pytest.raises(ValueError, match="exit_weights"):
        VerificationConfig(exit_weights=(1.0, 2.0))
    with pytest.raises(ValueError, match="exit_estimator"):
        VerificationConfig(exit_estimator="magic")
    with pytest.raises(ValueError, match="exit_threshold"):
        VerificationConfig(exit_threshold=1.5)
    assert not VerificationConfig(exit_weights=()).fast_exit


def test_a_calibration_stored_without_an_exit_model_runs_without_a_fast_exit(tmp_path):
    """An exit model belongs to the calibration it was fitted with: a manifest's calibration
    without one never borrows the code's defaults."""
    from logdesc_rt.network import bundled_model_dir

    runtime = json.loads((bundled_model_dir() / "manifest.json").read_text())["runtime"]
    for key in ("exit_weights", "exit_bias", "exit_threshold", "exit_estimator"):
        runtime["verification"].pop(key, None)
    assert not Registrar(_model_copy(tmp_path, runtime)).config.verification.fast_exit


def test_the_exit_threshold_is_where_the_calibration_pairs_exits_are_right_99_percent_of_the_time():
    """calibrate_exit on made-up hypotheses whose fitness separates right from wrong except for
    a few: the threshold admits no wrong exit beyond 1 %, and a real-scan wrong pose never exits."""
    from logdesc_rt.config import VERIFICATION_FEATURES

    calibrate_success = _calibrate_success()
    rng = np.random.default_rng(0)
    rows = []
    for index in range(400):
        right = index % 4 != 0
        fitness = rng.uniform(0.6, 1.0) if right else rng.uniform(0.0, 0.7)
        features = [0.0] * len(VERIFICATION_FEATURES)
        features[VERIFICATION_FEATURES.index("fitness")] = fitness
        group = "bunny_unbenchmarked" if index % 50 == 0 else "val_in_range"
        rows.append({"pair": f"{group}/{index:04d}", "group": group, "estimators": ["fsr"], "refined": True,
                     "features": features, "verified_right": right, "unrefined_right": right,
                     "unrefined_claimable": True})
    fitted = calibrate_success.calibrate_exit(rows, VerificationConfig())
    assert fitted.fast_exit and 0.0 < fitted.exit_threshold < 1.0
    outcomes = calibrate_success.flag_outcomes(rows, fitted)
    exits = [outcome for outcome in outcomes.values() if outcome["fast_exit"]]
    assert len(exits) > 100
    assert np.mean([outcome["refined_right"] for outcome in exits]) >= calibrate_success.EXIT_TARGET_PRECISION
    wrong_real = [row for row in rows if row["group"].startswith("bunny") and not row["verified_right"]]
    assert wrong_real and not any(outcomes[row["pair"]]["fast_exit"] for row in wrong_real)
    # Nothing separable: no exit at all.
    for row in rows:
        row["verified_right"] = row["unrefined_right"] = bool(rng.random() < 0.5)
    assert not calibrate_success.calibrate_exit(rows, VerificationConfig()).fast_exit


def test_thorough_verifies_every_candidate_even_where_the_fast_exit_is_sure(registrar, demo_pair):
    """register(thorough=True) is the full verification, one keyword away: the same result as a
    calibration without an exit model."""
    config = _exit_config(0.8)
    assert registrar.register(demo_pair.source, demo_pair.target, config=config).verification.fast_exit
    thorough = registrar.register(demo_pair.source, demo_pair.target, config=config, thorough=True)
    full = registrar.register(demo_pair.source, demo_pair.target, config={"verification": {"exit_weights": []}})
    assert not thorough.verification.fast_exit
    assert np.array_equal(thorough.transformation, full.transformation) and thorough.confidence == full.confidence
    assert not thorough.config.verification.fast_exit


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_bounded_scoring_queries_give_the_features_of_unbounded_ones(noise):
    """The scoring queries stop at the inlier distance (QUERY_BOUND_MARGIN): the features of a
    right pose, slightly and far wrong ones and a half-turn must be those of full nearest-
    neighbour searches, value for value. A bound that dropped an inlier would change them."""
    rng = np.random.default_rng(5)
    source = _plate_with_a_ridge(rng)
    truth = _rigid([0.3, -0.5, 0.9], [0.4, -0.2, 0.1])
    target = source @ truth[:3, :3].T + truth[:3, 3] + rng.normal(scale=noise, size=source.shape)
    matched = source[:50]
    verifier = PoseVerifier(source, target, matched, matched @ truth[:3, :3].T + truth[:3, 3], np.full(50, 0.5), 1.0)
    centre = source.mean(axis=0)
    poses = [truth, _turned(truth, 2.0, centre), _turned(truth, 20.0, centre), _turned(truth, 180.0, centre)]
    bounded = [verifier.features(pose) for pose in poses]
    verifier.query_bound = np.inf
    unbounded = [verifier.features(pose) for pose in poses]
    for got, expected in zip(bounded, unbounded, strict=True):
        assert np.array_equal(got, expected)
    # The poses span the features: all inliers, some, and few.
    fitness = [features[VERIFICATION_FEATURES.index("fitness")] for features in bounded]
    assert max(fitness) > 0.9 and min(fitness) < 0.5
