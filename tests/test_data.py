"""Training data: the PRNet protocol's ground truth, seeding, splits and the dataset's tensors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from logdesc_rt.config import GeometryConfig
from logdesc_rt.metrics import IGNORED
from logdesc_rt.synthetic import (
    MATCH_RADIUS_SPACINGS,
    NOISE_BOUND,
    PAPER_PROTOCOLS,
    RESAMPLED_PROTOCOLS,
    SOURCE_POINTS,
    SPACING_NEIGHBOUR,
)
from logdesc_rt.synthetic import PROTOCOLS as SHAPE_PROTOCOLS
from training.data import (
    MODELNET10_FOLDER,
    MODELNET40_SUBSET_FOLDER,
    PROTOCOLS,
    PairDataset,
    PairKey,
    ProtocolSchedule,
    TrainBatchSampler,
    fixed_pair_batches,
    load_modelnet,
    load_training_sources,
    make_pair,
    parse_protocol_mix,
    read_modelnet_h5,
    split_training_shapes,
    validation_keys,
)

DATA_ROOT = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _shape(count: int = 1024, seed: int = 0) -> np.ndarray:
    """A lumpy closed surface (no symmetry), points in the unit ball."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radius = 0.7 + 0.2 * directions[:, 0] ** 2 + 0.1 * directions[:, 1] * directions[:, 2]
    return directions * radius[:, None]


def _moved(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    return points @ pose[:3, :3].T + pose[:3, 3]


def _residuals(source, target, pose, gt_match_src) -> np.ndarray:
    matched = gt_match_src >= 0
    return np.linalg.norm(_moved(source[matched], pose) - target[gt_match_src[matched]], axis=1)


@pytest.mark.parametrize("protocol", SHAPE_PROTOCOLS)
def test_ground_truth_correspondences(protocol):
    shape = _shape()
    for seed in range(5):
        pair = make_pair(shape, protocol, np.random.default_rng(seed))
        residuals = _residuals(pair.source, pair.target, pair.T_gt, pair.gt_match_src)
        if protocol == "clean":
            assert pair.gt_match_src.min() >= 0 and len(pair.source) == 1024
            np.testing.assert_allclose(residuals, 0.0, atol=1e-12)
        elif protocol in RESAMPLED_PROTOCOLS:  # different samples: apart by up to 1.5 spacings
            assert residuals.max() <= NOISE_BOUND + MATCH_RADIUS_SPACINGS * _largest_spacing(shape) + 1e-12
        else:
            assert residuals.max() <= NOISE_BOUND + 1e-12
            assert residuals.mean() > 1e-3  # the noise is really there
        if protocol in PAPER_PROTOCOLS:
            assert pair.gt_match_src.min() >= -1 and pair.gt_match_tgt.min() >= -1  # nothing ignored
        # Network frame: same correspondences under the network-frame pose, lengths / scale.
        residuals_network = _residuals(
            pair.source_network, pair.target_network, pair.T_gt_network, pair.gt_match_src
        )
        np.testing.assert_allclose(residuals_network * pair.normalization.scale, residuals, atol=1e-9)
        # And the network pose maps back to the user pose exactly.
        np.testing.assert_allclose(pair.normalization.pose_to_user_frame(pair.T_gt_network), pair.T_gt, atol=1e-12)


def _largest_spacing(shape: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    distance, _ = cKDTree(shape).query(shape, k=SPACING_NEIGHBOUR + 1)
    return float(distance[:, SPACING_NEIGHBOUR].max())


@pytest.mark.parametrize("protocol", RESAMPLED_PROTOCOLS)
def test_resampled_pairs_share_no_point_and_label_like_real_scans(protocol):
    shape = _shape()
    for seed in range(5):
        pair = make_pair(shape, protocol, np.random.default_rng(seed))
        size = SOURCE_POINTS // 2 if protocol == "resampled" else round(0.75 * (SOURCE_POINTS // 2))
        assert pair.source.shape == (size, 3) and pair.target.shape == (size, 3)
        src, tgt = pair.gt_match_src, pair.gt_match_tgt
        matched = np.flatnonzero(src >= 0)
        np.testing.assert_array_equal(tgt[src[matched]], matched)  # one-to-one
        assert (src >= 0).sum() == (tgt >= 0).sum()
        assert 0.3 < np.mean(src >= 0) < 0.8 and np.mean(src == IGNORED) > 0.1
        if protocol == "resampled":  # full overlap: (almost) every point is near a counterpart
            assert np.mean(src == -1) < 0.02
        else:
            assert np.mean(src == -1) > 0.0

    # Different points indeed: the clean protocol's twin of a source point sits exactly on
    # the moved point; here no target point does.
    pair = make_pair(shape, "resampled", np.random.default_rng(0))
    from scipy.spatial import cKDTree

    gaps, _ = cKDTree(pair.target).query(_moved(pair.source, pair.T_gt), k=1)
    clean = make_pair(shape, "clean", np.random.default_rng(0))
    twins, _ = cKDTree(clean.target).query(_moved(clean.source, clean.T_gt), k=1)
    assert twins.max() < 1e-9 and np.median(gaps) > 0.5 * np.median(cKDTree(shape).query(shape, k=2)[0][:, 1])


def test_motion_ranges():
    shape = _shape()
    angles, translations = [], []
    for seed in range(200):
        pair = make_pair(shape, "clean", np.random.default_rng(seed))
        angles.append(pair.euler_zyx_deg)
        translations.append(pair.T_gt[:3, 3])
        # The drawn Euler angles are what scipy reads back from the rotation ('zyx', DCP).
        from scipy.spatial.transform import Rotation

        np.testing.assert_allclose(
            Rotation.from_matrix(pair.T_gt[:3, :3]).as_euler("zyx", degrees=True), pair.euler_zyx_deg, atol=1e-9
        )
    angles, translations = np.array(angles), np.array(translations)
    assert angles.min() >= 0 and angles.max() <= 45 and angles.max() > 40
    assert np.abs(translations).max() <= 0.5 and np.abs(translations).max() > 0.45


def test_matches_are_mutual_inverses_and_partial_sizes():
    shape = _shape()
    for seed in range(5):
        pair = make_pair(shape, "partial", np.random.default_rng(seed))
        assert pair.source.shape == (768, 3) and pair.target.shape == (768, 3)
        src, tgt = pair.gt_match_src, pair.gt_match_tgt
        assert 0 < (src >= 0).sum() < 768  # some overlap, not all
        assert (src >= 0).sum() == (tgt >= 0).sum()
        matched = np.flatnonzero(src >= 0)
        np.testing.assert_array_equal(tgt[src[matched]], matched)
        matched_t = np.flatnonzero(tgt >= 0)
        np.testing.assert_array_equal(src[tgt[matched_t]], matched_t)
        assert len(np.unique(src[matched])) == len(matched)  # one-to-one


def test_points_per_cloud_subsamples_before_the_pair():
    pair = make_pair(_shape(), "partial", np.random.default_rng(0), points_per_cloud=128)
    assert pair.source.shape == (96, 3) and pair.target.shape == (96, 3)
    assert _residuals(pair.source, pair.target, pair.T_gt, pair.gt_match_src).max() <= NOISE_BOUND
    clean = make_pair(_shape(), "clean", np.random.default_rng(0), points_per_cloud=128)
    assert clean.source.shape == (128, 3) and clean.gt_match_src.min() >= 0


def test_same_seed_same_pair_and_same_motion_across_protocols():
    shape = _shape()
    first = make_pair(shape, "noisy", np.random.default_rng([3, 0, 7]))
    again = make_pair(shape, "noisy", np.random.default_rng([3, 0, 7]))
    other = make_pair(shape, "noisy", np.random.default_rng([3, 1, 7]))
    np.testing.assert_array_equal(first.source, again.source)
    np.testing.assert_array_equal(first.target, again.target)
    np.testing.assert_array_equal(first.gt_match_src, again.gt_match_src)
    assert not np.allclose(first.T_gt, other.T_gt)
    partial = make_pair(shape, "partial", np.random.default_rng([3, 0, 7]))
    np.testing.assert_array_equal(first.T_gt, partial.T_gt)  # motion drawn first


@pytest.mark.parametrize("protocol", SHAPE_PROTOCOLS)
def test_any_orientation_turns_the_same_pair(protocol):
    """The whole-pair rotation is drawn last: the same pair, both clouds turned by one G."""
    shape = _shape()
    plain = make_pair(shape, protocol, np.random.default_rng([4, 0, 2]))
    turned = make_pair(shape, protocol, np.random.default_rng([4, 0, 2]), any_orientation=True)
    # Recover G from the sources (same points, same order) and check everything follows it.
    turn = np.linalg.lstsq(plain.source, turned.source, rcond=None)[0].T
    np.testing.assert_allclose(turn @ turn.T, np.eye(3), atol=1e-9)
    assert not np.allclose(turn, np.eye(3))
    np.testing.assert_allclose(turned.target, plain.target @ turn.T, atol=1e-12)
    np.testing.assert_array_equal(turned.gt_match_src, plain.gt_match_src)
    residuals = _residuals(turned.source, turned.target, turned.T_gt, turned.gt_match_src)
    np.testing.assert_allclose(residuals, _residuals(plain.source, plain.target, plain.T_gt, plain.gt_match_src),
                               atol=1e-9)
    # The size of the relative motion does not change, only its axis.
    angle = [np.trace(pair.T_gt[:3, :3]) for pair in (plain, turned)]
    assert angle[0] == pytest.approx(angle[1], abs=1e-9)


@pytest.mark.parametrize("protocol", ["partial", "resampled_partial"])
def test_any_relative_rotation_turns_the_target_alone_by_any_angle(protocol):
    """Drawn last: the same source, the target turned about its centroid, labels still true,
    and relative rotations far beyond the paper's 45 degrees per axis."""
    shape = _shape()
    angles = []
    for seed in range(12):
        plain = make_pair(shape, protocol, np.random.default_rng([5, 0, seed]), any_orientation=True)
        turned = make_pair(shape, protocol, np.random.default_rng([5, 0, seed]), any_orientation=True,
                           any_relative_rotation=True)
        np.testing.assert_array_equal(turned.source, plain.source)
        np.testing.assert_array_equal(turned.gt_match_src, plain.gt_match_src)
        np.testing.assert_allclose(turned.target.mean(axis=0), plain.target.mean(axis=0), atol=1e-12)
        residuals = _residuals(turned.source, turned.target, turned.T_gt, turned.gt_match_src)
        np.testing.assert_allclose(
            residuals, _residuals(plain.source, plain.target, plain.T_gt, plain.gt_match_src), atol=1e-9
        )
        cosine = (np.trace(turned.T_gt[:3, :3]) - 1.0) / 2.0
        angles.append(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
    # The paper's motion is at most ~70 degrees in all; uniform rotations exceed 90 degrees
    # with probability ~0.82, so 12 draws without one would be a broken turn.
    assert max(angles) > 120.0 and sum(angle > 90.0 for angle in angles) >= 5


def test_pair_dataset_any_orientation_turns_its_pairs():
    shapes = np.stack([_shape(), _shape()[::-1].copy()])
    key = PairKey(0, 1, "noisy", SOURCE_POINTS)
    plain = PairDataset(shapes, seed=3)[key]
    turned = PairDataset(shapes, seed=3, any_orientation=True)[key]
    assert not np.allclose(plain["T_gt_user"], turned["T_gt_user"])
    np.testing.assert_array_equal(plain["gt_match_src"], turned["gt_match_src"])
    # Same pair seen from another frame: the rotation angle of the motion is unchanged.
    assert np.trace(plain["T_gt_user"][:3, :3]) == pytest.approx(np.trace(turned["T_gt_user"][:3, :3]), abs=1e-6)


def test_protocol_mix_and_schedule():
    assert parse_protocol_mix("clean:1,partial:3") == {
        "clean": 0.25, "noisy": 0.0, "partial": 0.75, "resampled": 0.0, "resampled_partial": 0.0, "scan": 0.0,
    }
    # A protocol added later with weight 0 leaves an older mix's validation pairs as they were.
    old_mix = parse_protocol_mix("clean:0.1,noisy:0.3,partial:0.6")
    old_protocols = [key.protocol for key in validation_keys(251, 96, old_mix, 0)]
    assert old_protocols.count("partial") == 57 and old_protocols.count("clean") == 10
    assert parse_protocol_mix('{"noisy": 2}')["noisy"] == 1.0
    with pytest.raises(ValueError):
        parse_protocol_mix("dirty:1")
    schedule = ProtocolSchedule(
        mix=parse_protocol_mix("clean:0.25,partial:0.75"), points_per_cloud=1024, scan_points_per_cloud=768,
    )
    assert schedule.protocol_at(0, 0.2) == "clean" and schedule.protocol_at(0, 0.3) == "partial"
    assert schedule.points_at(0, "partial") == 1024 and schedule.points_at(0, "scan") == 768


def test_batch_sampler_is_resumable_and_uniform_per_batch():
    schedule = ProtocolSchedule(mix=parse_protocol_mix("clean:0.2,noisy:0.3,partial:0.5"))
    sampler = TrainBatchSampler(50, 4, schedule, seed=5)
    iterator = iter(sampler)
    batches = [next(iterator) for _ in range(30)]  # crosses two epoch boundaries (12 per epoch)
    resumed = iter(TrainBatchSampler(50, 4, schedule, seed=5, start_step=17))
    assert [next(resumed) for _ in range(13)] == batches[17:]
    for step, batch in enumerate(batches):
        assert batch == sampler.batch_keys(step)
        assert len({key.protocol for key in batch}) == 1 and len(batch) == 4
    epoch0 = [key.index for batch in batches[:12] for key in batch]
    assert len(set(epoch0)) == 48  # no shape twice within an epoch
    assert {key.protocol for batch in batches for key in batch} == set(PAPER_PROTOCOLS)


def test_validation_keys_are_fixed_and_proportional():
    mix = parse_protocol_mix("clean:0.2,noisy:0.3,partial:0.5")
    keys = validation_keys(40, 100, mix, seed=1)
    assert keys == validation_keys(40, 100, mix, seed=1)
    counts = {p: sum(k.protocol == p for k in keys) for p in PROTOCOLS}
    assert counts == {"clean": 20, "noisy": 30, "partial": 50, "resampled": 0, "resampled_partial": 0, "scan": 0}
    assert len(set(keys)) == 100  # shapes reused with another epoch word, never the same pair
    for batch in fixed_pair_batches(keys, 8):
        assert len({(k.protocol, k.points_per_cloud) for k in batch}) == 1 and len(batch) <= 8


def test_dataset_sample_tensors():
    shapes = np.stack([_shape(1024, seed) for seed in range(3)]).astype(np.float32)
    dataset = PairDataset(shapes, seed=9)
    sample = dataset[PairKey(0, 1, "partial", 1024)]
    assert (
        sample["src_edges"].shape == (768, GeometryConfig().umbrella_neighbours, GeometryConfig().edge_channels)
        and sample["src_edges"].dtype == np.float32
    )
    assert sample["tgt_points"].shape == (768, 3) and sample["src_normals"].shape == (768, 3)
    np.testing.assert_allclose(np.linalg.norm(sample["src_normals"], axis=1), 1.0, atol=1e-5)
    # Network-frame pose and points agree with the user-frame ones via the stored normalisation.
    from logdesc_rt.normalization import PairNormalization

    norm = PairNormalization(sample["source_centre"], sample["target_centre"], float(sample["scale"]))
    np.testing.assert_allclose(norm.source_to_network(sample["source_user"]), sample["src_points"], atol=1e-5)
    np.testing.assert_allclose(norm.pose_to_user_frame(sample["T_gt"].astype(np.float64)), sample["T_gt_user"],
                               atol=1e-5)
    residuals = _residuals(sample["source_user"], sample["target_user"], sample["T_gt_user"], sample["gt_match_src"])
    assert residuals.max() <= NOISE_BOUND
    again = dataset[PairKey(0, 1, "partial", 1024)]
    np.testing.assert_array_equal(sample["src_edges"], again["src_edges"])


def test_dataset_collates_into_a_batch():
    torch = pytest.importorskip("torch")
    from torch.utils.data import DataLoader

    shapes = np.stack([_shape(1024, seed) for seed in range(4)]).astype(np.float32)
    keys = [[PairKey(0, i, "noisy", 128) for i in range(4)]]
    batch = next(iter(DataLoader(PairDataset(shapes), batch_sampler=keys)))
    assert (
        batch["src_edges"].shape == (4, 128, GeometryConfig().umbrella_neighbours, GeometryConfig().edge_channels)
        and batch["src_edges"].dtype == torch.float32
    )
    assert batch["gt_match_src"].dtype == torch.int64 and batch["T_gt"].shape == (4, 4, 4)
    assert batch["protocol"] == ["noisy"] * 4


# ----------------------------------------------------------------------------- real data
@pytest.fixture(scope="module")
def data_root(shared_data) -> Path:
    return shared_data


def test_read_modelnet_h5_point_counts(data_root):
    points, labels, names = read_modelnet_h5(data_root / MODELNET10_FOLDER, "train")
    assert points.shape == (3991, 1024, 3) and points.dtype == np.float32
    assert labels.shape == (3991,) and labels.max() < len(names) == 10
    points40, _, _ = read_modelnet_h5(data_root / MODELNET40_SUBSET_FOLDER, "train")
    assert points40.shape == (1019, 2048, 3)


def test_read_modelnet_h5_resolves_prefixed_listing(data_root, tmp_path):
    import shutil

    source = data_root / MODELNET10_FOLDER
    shutil.copy(source / "shape_names.txt", tmp_path)
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "ply_data_test0.h5").symlink_to(source / "ply_data_test0.h5")
    # A listed path is resolved relative to the folder ...
    (tmp_path / "test_files.txt").write_text("sub/ply_data_test0.h5\n")
    assert read_modelnet_h5(tmp_path, "test")[0].shape == (908, 1024, 3)
    # ... and a prefix that is not there (the original release's "data/...") by its bare name.
    (tmp_path / "ply_data_test0.h5").symlink_to(source / "ply_data_test0.h5")
    (tmp_path / "test_files.txt").write_text("data/modelnet10/ply_data_test0.h5\n")
    assert read_modelnet_h5(tmp_path, "test")[0].shape == (908, 1024, 3)


def test_training_split_is_disjoint_and_never_reads_test(data_root):
    with pytest.raises(ValueError, match="evaluation split"):
        load_training_sources(data_root, [(MODELNET10_FOLDER, "test")])
    shapes = split_training_shapes(load_training_sources(data_root), 0.05, seed=0)
    assert shapes.train.shape[1:] == (1024, 3) and shapes.val.shape[1:] == (1024, 3)
    assert set(shapes.train_ids).isdisjoint(shapes.val_ids)
    # By model name too: the ModelNet40 subset repeats 154 ModelNet10 training models.
    assert shapes.train_names.isdisjoint(shapes.val_names)
    assert 200 <= len(shapes.val) <= 260 and len(shapes.train) + len(shapes.val) <= 3991 + 1019
    # Fixed: same seed, same split.
    again = split_training_shapes(load_training_sources(data_root), 0.05, seed=0)
    assert again.val_ids == shapes.val_ids
    # No training or validation model is a ModelNet10 test model.
    test_names = set(load_modelnet(data_root / MODELNET10_FOLDER, "test").shape_ids)
    assert test_names.isdisjoint(shapes.train_names | shapes.val_names)


def test_real_shape_pairs(data_root):
    shapes = split_training_shapes(load_training_sources(data_root), 0.05, seed=0)
    dataset = PairDataset(shapes.val[:4], seed=0)
    for protocol in SHAPE_PROTOCOLS:
        sample = dataset[PairKey(0, 2, protocol, 1024)]
        residuals = _residuals(
            sample["source_user"], sample["target_user"], sample["T_gt_user"], sample["gt_match_src"]
        )
        bound = 1e-9 if protocol == "clean" else NOISE_BOUND
        if protocol in RESAMPLED_PROTOCOLS:
            bound += MATCH_RADIUS_SPACINGS * _largest_spacing(shapes.val[2].astype(np.float64))
        assert residuals.max() <= bound
        expected = {"partial": 768, "resampled": 512, "resampled_partial": 384}.get(protocol, 1024)
        assert sample["src_edges"].shape == (
            expected, GeometryConfig().umbrella_neighbours, GeometryConfig().edge_channels
        )


def test_scan_shapes_drawn_by_class_weight_deterministically():
    """--scan-shape-weighting sqrt-class: a class of c shapes weighs sqrt(c) (its shapes
    1/sqrt(c) each), the same key always draws the same shape, "uniform" keeps index % count,
    and an unknown weighting is refused by name."""
    from training.data import DenseShapes

    names = [f"airplane_{i:04d}" for i in range(16)] + [
        "bench_0001", "bench_0002", "bench_0003", "bench_0004", "lamp_0001"
    ]
    dense = DenseShapes(np.zeros((len(names), 4, 3), np.float32), np.zeros((len(names), 4, 3), np.float32), names)
    weights = dense.draw_weights("sqrt-class")
    classes = np.array(dense.class_names)
    # Class totals 4 : 2 : 1 (sqrt of 16, 4, 1).
    assert np.allclose([weights[classes == c].sum() for c in ("airplane", "bench", "lamp")], np.array([4, 2, 1]) / 7)
    assert np.allclose(dense.draw_weights("uniform"), 1 / len(names))
    with pytest.raises(ValueError, match="weighting"):
        dense.draw_weights("balanced")
    shapes = np.zeros((3, 1024, 3), np.float32)
    weighted = PairDataset(shapes, seed=4, dense=dense, scan_shape_weighting="sqrt-class", geometry_on_device=True)
    uniform = PairDataset(shapes, seed=4, dense=dense, geometry_on_device=True)
    keys = [(PairKey(epoch, index, "scan", 256), [4, epoch, index]) for epoch in range(300) for index in range(3)]
    drawn = np.array([weighted.scan_shape(key, words) for key, words in keys])
    assert np.array_equal(drawn, [weighted.scan_shape(key, words) for key, words in keys])
    assert abs(np.mean(classes[drawn] == "airplane") - 4 / 7) < 0.06
    assert [uniform.scan_shape(key, words) for key, words in keys[:5]] == [
        key.index % len(names) for key, _ in keys[:5]
    ]
    with pytest.raises(ValueError, match="weighting"):
        PairDataset(shapes, dense=dense, scan_shape_weighting="balanced")


@pytest.mark.parametrize("protocol", ["noisy", "partial", "resampled_partial"])
def test_working_size_cuts_each_cloud_as_register_does_and_labels_from_geometry(protocol):
    """make_pair(working_size=...): a cloud above the working size is cut to exactly that many
    points by the runtime's working subset (each cloud on its own), a smaller one is kept whole;
    the labels are one-to-one and every matched pair lies within a few spacings of its partner
    under the truth; the same seed, the same pair."""
    from logdesc_rt.config import NormalizationConfig
    from logdesc_rt.sampling import working_subset

    shape, rng_words = _shape(), [3, 1]
    whole = make_pair(shape, protocol, np.random.default_rng(rng_words))
    cut = make_pair(shape, protocol, np.random.default_rng(rng_words), working_size=512)
    for cloud, cloud_cut in ((whole.source, cut.source), (whole.target, cut.target)):
        if len(cloud) > 512:
            assert len(cloud_cut) == 512
            np.testing.assert_array_equal(cloud_cut, cloud[working_subset(cloud, 512, "fps", NormalizationConfig())])
        else:
            np.testing.assert_array_equal(cloud_cut, cloud)
    src, tgt = cut.gt_match_src, cut.gt_match_tgt
    matched = np.flatnonzero(src >= 0)
    assert len(matched) > 50
    np.testing.assert_array_equal(tgt[src[matched]], matched)
    spacing = np.median(np.sort(np.linalg.norm(shape[:, None] - shape[None], axis=-1), axis=1)[:, 1])
    assert _residuals(cut.source, cut.target, cut.T_gt, src).max() <= 3 * spacing + 2 * NOISE_BOUND
    again = make_pair(shape, protocol, np.random.default_rng(rng_words), working_size=512)
    np.testing.assert_array_equal(again.source, cut.source)
    np.testing.assert_array_equal(again.gt_match_src, cut.gt_match_src)
