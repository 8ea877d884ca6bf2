"""Training and evaluation data: ModelNet HDF5 shapes -> registration pairs -> network inputs.

Pipeline of one pair (the paper's protocol, after PRNet; /work/shared/data/README.md):

1. :func:`read_modelnet_h5` loads shapes from the ``modelnet40_ply_hdf5_2048`` layout.
2. :func:`make_pair` builds a (source, target) pair in the *user frame* (the dataset's unit
   sphere): source = the first 1024 points, target = source rotated by Euler angles drawn
   uniformly in [0, 45] degrees per axis (scipy ``"zyx"``, as DCP/PRNet) and translated
   uniformly in [-0.5, 0.5] per axis; both randomly permuted; optional Gaussian noise
   (sigma 0.01, clipped to +-0.05) and partial cropping (768 points nearest to a far point).
3. :class:`logdesc_rt.normalization.PairNormalization` maps the pair into the *network frame*
   exactly as the runtime does (one source of truth), and the ground-truth pose is
   re-expressed there.
4. :class:`PairDataset` runs :func:`logdesc_rt.geometry.compute_geometry` on both network-frame
   clouds and returns a dict of arrays ready for ``default_collate``.

Randomness: a pair is a pure function of ``(seed, epoch, shape index, protocol, points)``. The
item for shape i in epoch e draws from ``np.random.default_rng([seed, e, i])``, so results are
reproducible and DataLoader workers never share RNG state. Protocols are chosen per *batch*
(:class:`TrainBatchSampler`) so that all clouds of a batch have the same size and stack into
(B, N, ...) tensors without padding (clean/noisy clouds have ``points_per_cloud`` points,
partial ones ``round(0.75 * points_per_cloud)``).

Data hygiene: ModelNet10's *test* split is reserved for :mod:`training.evaluate`;
:func:`load_training_sources` refuses it. Validation shapes are carved from the training shapes
by *shape name* (the ModelNet40 subset and ModelNet10 train share 154 models, e.g.
``bathtub_0001``), so no validation model is ever trained on under either source.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Mapping, NamedTuple, Sequence

import numpy as np

from logdesc_rt.config import GeometryConfig, NormalizationConfig
from logdesc_rt.errors import InvalidPointCloudError
from logdesc_rt.geometry import compute_geometry

# The pair protocol lives with the runtime, which the demo, tests and benchmarks share.
from logdesc_rt.scan_simulation import SCAN_PROTOCOL, make_scan_pair
from logdesc_rt.synthetic import PAPER_PROTOCOLS, SOURCE_POINTS, Pair, make_pair
from logdesc_rt.synthetic import PROTOCOLS as SHAPE_PROTOCOLS

# Every protocol training can draw: the 1024-point shape protocols of logdesc_rt.synthetic, and
# simulated range scans of the dense shapes (logdesc_rt.scan_simulation).
PROTOCOLS: tuple[str, ...] = SHAPE_PROTOCOLS + (SCAN_PROTOCOL,)

try:  # The pair construction is usable without torch (e.g. by NumPy-only benchmarks).
    from torch.utils.data import Dataset as _TorchDataset
    from torch.utils.data import Sampler as _TorchSampler
except ImportError:  # pragma: no cover - torch is a training dependency
    _TorchDataset = object  # type: ignore[assignment,misc]
    _TorchSampler = object  # type: ignore[assignment,misc]

__all__ = [
    "DEFAULT_DATA_ROOT",
    "DENSE_FOLDER",
    "DenseShapes",
    "MODELNET10_FOLDER",
    "MODELNET40_SUBSET_FOLDER",
    "PAPER_PROTOCOLS",
    "PROTOCOLS",
    "ModelNetSplit",
    "Pair",
    "PairDataset",
    "PairKey",
    "SCAN_PROTOCOL",
    "ProtocolSchedule",
    "TrainBatchSampler",
    "TrainingShapes",
    "fixed_pair_batches",
    "load_dense_shapes",
    "SCAN_SHAPE_WEIGHTINGS",
    "load_modelnet",
    "load_training_sources",
    "make_pair",
    "parse_protocol_mix",
    "read_modelnet_h5",
    "split_training_shapes",
    "run_split",
    "split_train_val_test",
    "validation_keys",
]

# ----------------------------------------------------------------------------- constants
DEFAULT_DATA_ROOT = Path(__file__).resolve().parents[1].parent / "shared" / "data"
DEFAULT_VAL_FRACTION = 0.05  # of each training source's shapes, held out for validation
MODELNET10_FOLDER = "modelnet10_hdf5_1024"
MODELNET40_SUBSET_FOLDER = "modelnet40_subset_hdf5_2048"
DENSE_FOLDER = "modelnet40_subset_10k"  # the ModelNet40 subset's shapes, 10,000 points with normals

# Seed-sequence "epochs" reserved for streams other than training epochs (far above any
# real epoch count), so that e.g. validation pairs never coincide with a training pair.
VALIDATION_EPOCH = 1_000_000_007
_SPLIT_STREAM = 1_000_000_009
_SAMPLER_STREAM = 2**32 - 1  # third seed word of the batch sampler (shape indices are smaller)


# ----------------------------------------------------------------------------- reading
@dataclass(frozen=True)
class ModelNetSplit:
    """One split of a ModelNet HDF5 folder.

    Attributes:
        points: (S, P, 3) float32 shapes (P = 1024 or 2048 depending on the release).
        labels: (S,) int64 class indices into ``class_names``.
        class_names: the lines of ``shape_names.txt``.
        shape_ids: (S,) per-shape identifiers such as ``"chair_0890"`` when the files carry a
            ``shape_name`` dataset, else ``"<split>_<index>"``.
    """

    points: np.ndarray
    labels: np.ndarray
    class_names: list[str]
    shape_ids: list[str]


def _split_files(folder: Path, split: str) -> list[Path]:
    """The h5 files of a split: ``<split>_files.txt`` entries resolved against ``folder``.

    The original release lists paths like ``data/modelnet40_ply_hdf5_2048/ply_data_train0.h5``;
    only the file name is reliable, so an entry is tried as given (relative to the folder),
    then by its bare name in the folder.
    """
    listing = folder / f"{split}_files.txt"
    if listing.is_file():
        entries = [line.strip() for line in listing.read_text().splitlines() if line.strip()]
    else:  # fall back to the conventional name
        entries = [f"ply_data_{split}0.h5"]
    files = []
    for entry in entries:
        candidates = [folder / entry, folder / Path(entry).name]
        found = next((path for path in candidates if path.is_file()), None)
        if found is None:
            raise FileNotFoundError(
                f"{listing}: lists {entry!r}, but neither {candidates[0]} nor {candidates[1]} exists"
            )
        files.append(found)
    if not files:
        raise FileNotFoundError(f"{listing}: lists no h5 file")
    return files


def load_modelnet(folder, split: str) -> ModelNetSplit:
    """Read every h5 file of ``split`` in a ModelNet HDF5 folder (any points per shape)."""
    import h5py  # training/evaluation dependency only

    folder = Path(folder)
    points, labels, shape_ids = [], [], []
    for path in _split_files(folder, split):
        with h5py.File(path, "r") as handle:
            data = np.asarray(handle["data"][:], dtype=np.float32)
            points.append(data)
            labels.append(np.asarray(handle["label"][:]).reshape(-1).astype(np.int64))
            if "shape_name" in handle:
                names = [
                    name.decode() if isinstance(name, bytes) else str(name)
                    for name in handle["shape_name"][:]
                ]
            else:
                start = sum(len(p) for p in points[:-1])
                names = [f"{split}_{start + index}" for index in range(len(data))]
            shape_ids.extend(names)
    point_counts = {p.shape[1] for p in points}
    if len(point_counts) != 1:
        # Different files of one split with different point counts: keep the common prefix.
        common = min(point_counts)
        points = [p[:, :common] for p in points]
    names_file = folder / "shape_names.txt"
    class_names = (
        [line.strip() for line in names_file.read_text().splitlines() if line.strip()]
        if names_file.is_file()
        else []
    )
    return ModelNetSplit(
        points=np.concatenate(points, axis=0),
        labels=np.concatenate(labels, axis=0),
        class_names=class_names,
        shape_ids=shape_ids,
    )


def read_modelnet_h5(folder, split: str) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Read a ModelNet HDF5 split (``<split>_files.txt`` / ``ply_data_<split>0.h5`` layout).

    Args:
        folder: directory holding ``<split>_files.txt``, the h5 files and ``shape_names.txt``.
        split: ``"train"`` or ``"test"`` (any name with a ``<split>_files.txt``).

    Returns:
        points (S, P, 3) float32 (P as stored: 1024 for ModelNet10 here, 2048 for ModelNet40),
        labels (S,) int64 class indices, and the class names of ``shape_names.txt``.
        Per-shape identifiers are in :func:`load_modelnet`'s ``shape_ids``.
    """
    split_data = load_modelnet(folder, split)
    return split_data.points, split_data.labels, split_data.class_names


# ----------------------------------------------------------------------------- shapes
@dataclass(frozen=True)
class TrainingShapes:
    """Training and validation shapes (first 1024 points of each), with their provenance.

    Attributes:
        train: (S_train, 1024, 3) float32.
        val: (S_val, 1024, 3) float32.
        train_ids / val_ids: ``"<source folder>/<shape id>"`` per shape.
        train_names / val_names: shape ids without the folder (the model identity used to
            keep the two sets disjoint across sources).
    """

    train: np.ndarray
    val: np.ndarray
    train_ids: list[str]
    val_ids: list[str]

    @property
    def train_names(self) -> set[str]:
        return {identifier.split("/", 1)[1] for identifier in self.train_ids}

    @property
    def val_names(self) -> set[str]:
        return {identifier.split("/", 1)[1] for identifier in self.val_ids}


def load_training_sources(
    data_root=DEFAULT_DATA_ROOT,
    sources: Sequence[tuple[str, str]] = ((MODELNET10_FOLDER, "train"), (MODELNET40_SUBSET_FOLDER, "train")),
) -> list[tuple[str, ModelNetSplit]]:
    """Load the training sources, each truncated to its first 1024 points per shape.

    Raises:
        ValueError: a source asks for ModelNet10's test split (reserved for evaluation).
    """
    loaded = []
    for folder, split in sources:
        # Hygiene guard: evaluation pairs come from ModelNet10's test split; it must never
        # feed training or validation (model selection) in any way.
        if split == "test" or (folder == MODELNET10_FOLDER and split != "train"):
            raise ValueError(f"training may not read {folder}/{split}: it is the evaluation split")
        data = load_modelnet(Path(data_root) / folder, split)
        if data.points.shape[1] < SOURCE_POINTS:
            raise ValueError(f"{folder}/{split}: {data.points.shape[1]} points per shape, need {SOURCE_POINTS}")
        truncated = ModelNetSplit(
            points=np.ascontiguousarray(data.points[:, :SOURCE_POINTS]),
            labels=data.labels,
            class_names=data.class_names,
            shape_ids=data.shape_ids,
        )
        loaded.append((folder, truncated))
    return loaded


def split_training_shapes(
    sources: Sequence[tuple[str, ModelNetSplit]], val_fraction: float = DEFAULT_VAL_FRACTION, seed: int = 0
) -> TrainingShapes:
    """Carve a fixed validation set from the training sources.

    ``val_fraction`` of each source's shapes (at least one) is drawn with
    ``default_rng([seed, _SPLIT_STREAM, source index])``; then every shape whose id (model
    name) is a validation name is removed from training in *all* sources, since the same
    model can appear in two releases.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    val_names: set[str] = set()
    val_parts, val_ids = [], []
    for source_index, (folder, data) in enumerate(sources):
        count = len(data.points)
        val_count = max(1, round(val_fraction * count)) if val_fraction > 0 else 0
        chosen = np.sort(
            np.random.default_rng([seed, _SPLIT_STREAM, source_index]).permutation(count)[:val_count]
        )
        # Skip names already taken by an earlier source's validation set (same model twice).
        chosen = [int(i) for i in chosen if data.shape_ids[i] not in val_names]
        val_names.update(data.shape_ids[i] for i in chosen)
        val_parts.append(data.points[chosen])
        val_ids.extend(f"{folder}/{data.shape_ids[i]}" for i in chosen)
    train_parts, train_ids = [], []
    for folder, data in sources:
        keep = [i for i, name in enumerate(data.shape_ids) if name not in val_names]
        train_parts.append(data.points[keep])
        train_ids.extend(f"{folder}/{data.shape_ids[i]}" for i in keep)
    return TrainingShapes(
        train=np.ascontiguousarray(np.concatenate(train_parts, axis=0)),
        val=np.ascontiguousarray(np.concatenate(val_parts, axis=0)),
        train_ids=train_ids,
        val_ids=val_ids,
    )


@dataclass(frozen=True)
class DenseShapes:
    """Dense shapes with normals, for simulated range scans (:mod:`logdesc_rt.scan_simulation`).

    Attributes:
        points: (S, P, 3) float32, unit sphere (P = 10,000 in ``modelnet40_subset_10k``).
        normals: (S, P, 3) float32 unit normals, signs not guaranteed.
        names: (S,) shape ids such as ``"airplane_0001"`` (the same ids as the ModelNet folders).
    """

    points: np.ndarray
    normals: np.ndarray
    names: list[str]

    def subset(self, names: set[str]) -> "DenseShapes":
        """The shapes whose id is in ``names``, in file order."""
        keep = [index for index, name in enumerate(self.names) if name in names]
        return DenseShapes(self.points[keep], self.normals[keep], [self.names[index] for index in keep])

    @property
    def class_names(self) -> list[str]:
        """(S,) each shape's class: its id without the number (``"airplane_0001"`` -> ``"airplane"``)."""
        return [name.rsplit("_", 1)[0] for name in self.names]

    def draw_weights(self, weighting: str) -> np.ndarray:
        """(S,) probabilities of drawing each shape for a scan pair, summing to 1.

        ``"uniform"``: every shape alike, so a class counts as often as it has shapes (the
        ModelNet40 subset is 61 % airplanes). ``"sqrt-class"``: each shape 1 / sqrt(its class's
        count), so a class of c shapes weighs sqrt(c): airplanes fall to about a quarter and the
        classes of a few shapes each rise, without any one shape repeated as often as uniform
        classes would repeat it.
        """
        if weighting not in SCAN_SHAPE_WEIGHTINGS:
            raise ValueError(f"scan shape weighting {weighting!r}: expected one of {SCAN_SHAPE_WEIGHTINGS}")
        classes = self.class_names
        if weighting == "uniform":
            weights = np.ones(len(classes))
        else:
            counts = {name: classes.count(name) for name in set(classes)}
            weights = np.array([1.0 / np.sqrt(counts[name]) for name in classes])
        return weights / weights.sum()


SCAN_SHAPE_WEIGHTINGS = ("uniform", "sqrt-class")
SHAPE_DRAW_STREAM = 17  # the last word of the generator that draws a weighted scan pair's shape


def load_dense_shapes(data_root=DEFAULT_DATA_ROOT) -> DenseShapes:
    """Read ``modelnet40_subset_10k/train.h5`` (../shared/data/README.md, "Dense shapes")."""
    import h5py

    with h5py.File(Path(data_root) / DENSE_FOLDER / "train.h5", "r") as handle:
        points = (handle["points_u16"][:].astype(np.float32) / 32767.5 - 1.0).astype(np.float32)
        normals = handle["normals_i8"][:].astype(np.float32) / 127.0
        names = [name.decode() if isinstance(name, bytes) else str(name) for name in handle["shape_name"][:]]
    normals /= np.maximum(np.linalg.norm(normals, axis=2, keepdims=True), 1e-12)
    return DenseShapes(points=points, normals=normals, names=names)


@dataclass(frozen=True)
class ThreeWaySplit:
    """Training shapes split three ways by shape name (:func:`split_train_val_test`).

    Attributes:
        shapes: train and validation shapes of the 1024-point sources.
        test_names: shape ids held out of training and validation in every source.
    """

    shapes: TrainingShapes
    test_names: frozenset[str]


def split_train_val_test(
    sources: Sequence[tuple[str, ModelNetSplit]], val_fraction: float = DEFAULT_VAL_FRACTION, seed: int = 1,
    test_seed: int = 0
) -> ThreeWaySplit:
    """v4's split: test = the shapes v3 validated on, validation = a fresh draw from the rest.

    The test names are :func:`split_training_shapes` ``(sources, val_fraction, test_seed)``'s
    validation names, i.e. the shapes v3 (trained with seed 0) never trained on, so that v3 and
    v4 can be compared on shapes neither saw. Validation is then drawn the same way with ``seed``
    from the remaining shapes, and training is the rest; all by shape name across sources (the
    dense shapes of :func:`load_dense_shapes` follow the same names).
    """
    test_names = split_training_shapes(sources, val_fraction, test_seed).val_names
    remaining = []
    for folder, data in sources:
        keep = [index for index, name in enumerate(data.shape_ids) if name not in test_names]
        remaining.append((folder, ModelNetSplit(
            points=data.points[keep],
            labels=data.labels[keep],
            class_names=data.class_names,
            shape_ids=[data.shape_ids[index] for index in keep],
        )))
    return ThreeWaySplit(shapes=split_training_shapes(remaining, val_fraction, seed), test_names=frozenset(test_names))


SPLITS = ("v3", "three-way")


def run_split(
    sources: Sequence[tuple[str, ModelNetSplit]], split: str = "v3", val_fraction: float = DEFAULT_VAL_FRACTION,
    seed: int = 0,
):
    """The training / validation shapes of a run (``training.train``'s ``--split``,
    ``--val-fraction`` and ``--seed``): "v3" is :func:`split_training_shapes`, "three-way" the
    training and validation part of :func:`split_train_val_test`. Training and evaluation both
    carve their split here, so ``--split val`` evaluates on the shapes the run validated on."""
    if split == "three-way":
        return split_train_val_test(sources, val_fraction, seed).shapes
    if split == "v3":
        return split_training_shapes(sources, val_fraction, seed)
    raise ValueError(f"split {split!r}: expected one of {SPLITS}")


# ----------------------------------------------------------------------------- protocol mix
def parse_protocol_mix(text: str | Mapping[str, float]) -> dict[str, float]:
    """Parse ``"clean:0.2,noisy:0.3,partial:0.5"`` (or a JSON object, or a dict); normalised.

    A bare protocol name means 100 % of it.
    """
    if isinstance(text, Mapping):
        raw = dict(text)
    else:
        text = text.strip()
        if text.startswith("{"):
            import json

            raw = json.loads(text)
        else:
            raw = {}
            for part in text.split(","):
                name, _, weight = part.partition(":")
                raw[name.strip()] = float(weight) if weight.strip() else 1.0
    unknown = set(raw) - set(PROTOCOLS)
    if unknown:
        raise ValueError(f"unknown protocol(s) {sorted(unknown)} in mix; expected {PROTOCOLS}")
    weights = {name: float(raw.get(name, 0.0)) for name in PROTOCOLS}
    if any(w < 0 for w in weights.values()) or sum(weights.values()) <= 0:
        raise ValueError(f"protocol mix needs non-negative weights with a positive sum: {raw}")
    total = sum(weights.values())
    return {name: weight / total for name, weight in weights.items()}


@dataclass(frozen=True)
class ProtocolSchedule:
    """Protocol mix and cloud size of the training batches.

    Every batch draws its protocol from ``mix``; clouds have ``points_per_cloud`` points (1024 =
    the paper's protocol), scan pairs ``scan_points_per_cloud`` if set.
    """

    mix: Mapping[str, float]
    points_per_cloud: int = SOURCE_POINTS
    scan_points_per_cloud: int | None = None

    def points_at(self, step: int, protocol: str | None = None) -> int:
        """Cloud size of a batch of ``protocol`` (``step`` is kept for the sampler's call)."""
        if protocol == SCAN_PROTOCOL and self.scan_points_per_cloud is not None:
            return self.scan_points_per_cloud
        return self.points_per_cloud

    def protocol_at(self, step: int, uniform: float) -> str:
        """Inverse-CDF draw of the step's protocol from a uniform number in [0, 1)."""
        cumulative = 0.0
        mix = self.mix
        for name in PROTOCOLS:
            cumulative += mix.get(name, 0.0)
            if uniform < cumulative:
                return name
        return max(mix, key=mix.get)  # rounding at the top end


# ----------------------------------------------------------------------------- dataset
class PairKey(NamedTuple):
    """Everything that determines one pair: its RNG words, protocol and size."""

    epoch: int
    index: int  # shape index in the dataset
    protocol: str
    points_per_cloud: int = SOURCE_POINTS


class PairDataset(_TorchDataset):
    """Registration pairs with network inputs, indexed by :class:`PairKey`.

    ``dataset[PairKey(e, i, protocol, n)]`` builds the pair of shape i with
    ``np.random.default_rng([seed, e, i])`` and returns a dict (``N``/``M`` points, ``k``
    neighbours, network units unless noted):

    - ``src_edges`` (N, k, 15) float32, ``src_points`` (N, 3) float32, ``src_normals``
      (N, 3) float32, and the same three ``tgt_*`` for the target;
    - ``gt_match_src`` (N,) int64, ``gt_match_tgt`` (M,) int64 (-1 = no counterpart, -2 =
      ignored: see :mod:`logdesc_rt.synthetic`'s resampled protocols);
    - ``T_gt`` (4, 4) float32 network-frame pose source -> target;
    - ``T_gt_user`` (4, 4) float64, ``source_user`` (N, 3) / ``target_user`` (M, 3) float64:
      the raw clouds and pose in the user frame, for evaluation;
    - ``source_centre``, ``target_centre`` (3,) float64 and ``scale`` () float64: the
      :class:`PairNormalization`, to map a predicted pose back to the user frame;
    - ``protocol`` str, ``epoch`` int, ``index`` int.

    Geometry that fails on a degenerate draw (very rare) is retried with
    ``default_rng([seed, e, i, attempt])``. With ``any_orientation`` every pair has both
    clouds turned by a random rotation, and with ``any_relative_rotation`` the target is then
    turned alone, so relative rotations are of any size (see
    :func:`logdesc_rt.synthetic.make_pair`).
    """

    def __init__(
        self,
        shapes: np.ndarray,
        seed: int = 0,
        geometry_config: GeometryConfig = GeometryConfig(),
        normalization_config: NormalizationConfig = NormalizationConfig(),
        name: str = "train",
        any_orientation: bool = False,
        geometry_on_device: bool = False,
        any_relative_rotation: bool = False,
        dense: DenseShapes | None = None,
        scan_shape_weighting: str = "uniform",
        working_size: int | None = None,
    ) -> None:
        if scan_shape_weighting not in SCAN_SHAPE_WEIGHTINGS:
            raise ValueError(f"scan shape weighting {scan_shape_weighting!r}: expected one of {SCAN_SHAPE_WEIGHTINGS}")
        shapes = np.asarray(shapes, dtype=np.float32)
        if shapes.ndim != 3 or shapes.shape[2] != 3 or shapes.shape[1] < SOURCE_POINTS:
            raise ValueError(f"shapes must be (S, P >= {SOURCE_POINTS}, 3), got {shapes.shape}")
        self.shapes = shapes
        self.seed = int(seed)
        self.geometry_config = geometry_config
        self.normalization_config = normalization_config
        self.name = name
        self.any_orientation = bool(any_orientation)
        self.any_relative_rotation = bool(any_relative_rotation)
        # True: samples carry points only; training computes the geometry for the whole batch
        # on its device (training/geometry_torch.py), where workers could not keep a GPU fed.
        self.geometry_on_device = bool(geometry_on_device)
        # Simulated scans ("scan" keys) are cut from these: shape key.index modulo their count
        # ("uniform"), or drawn with DenseShapes.draw_weights (``scan_shape_weighting``).
        self.dense = dense
        self.scan_shape_weighting = scan_shape_weighting
        # Shape pairs are cut to this many points per cloud as the runtime cuts them (None: the
        # protocol's own sizes); scan pairs take their size from their key.
        self.working_size = working_size
        self._scan_shape_cumulative = (
            None if dense is None or scan_shape_weighting == "uniform"
            else np.cumsum(dense.draw_weights(scan_shape_weighting))
        )

    def __len__(self) -> int:
        return len(self.shapes)

    def pair(self, key: PairKey, attempt: int = 0) -> Pair:
        """The :class:`Pair` of ``key`` (no geometry)."""
        words = [self.seed, int(key.epoch), int(key.index)] + ([attempt] if attempt else [])
        if key.protocol == SCAN_PROTOCOL:
            return self._scan_pair(key, words)
        return make_pair(
            self.shapes[key.index],
            key.protocol,
            np.random.default_rng(words),
            points_per_cloud=key.points_per_cloud,
            normalization_config=self.normalization_config,
            any_orientation=self.any_orientation,
            any_relative_rotation=self.any_relative_rotation,
            working_size=self.working_size,
        )

    def scan_shape(self, key: PairKey, words: list[int]) -> int:
        """The dense shape of a scan pair: ``key.index % len(dense)`` ("uniform"), else drawn
        by the weighting from ``default_rng(words + [SHAPE_DRAW_STREAM])`` (the same key, the
        same shape)."""
        if self._scan_shape_cumulative is None:
            return int(key.index) % len(self.dense.points)
        draw = np.random.default_rng(words + [SHAPE_DRAW_STREAM]).random()
        return int(min(np.searchsorted(self._scan_shape_cumulative, draw, side="right"), len(self.dense.points) - 1))

    def _scan_pair(self, key: PairKey, words: list[int]) -> Pair:
        """Two simulated scans of dense shape :meth:`scan_shape`, exactly
        ``key.points_per_cloud`` points each (the next shape if one is too sparse)."""
        if self.dense is None:
            raise ValueError(f"{self.name}: a {SCAN_PROTOCOL!r} pair needs the dense shapes (dense=...)")
        last_error: Exception | None = None
        first = self.scan_shape(key, words)
        for offset in range(4):
            index = (first + offset) % len(self.dense.points)
            try:
                return make_scan_pair(
                    self.dense.points[index],
                    self.dense.normals[index],
                    np.random.default_rng(words + [offset]),
                    points_per_cloud=key.points_per_cloud,
                    normalization_config=self.normalization_config,
                    min_points=self.geometry_config.min_points,
                    exact_size=True,
                )
            except ValueError as error:  # too sparse for two views of that size
                last_error = error
        raise RuntimeError(f"{self.name} scan pair {key}: four shapes too sparse") from last_error

    def __getitem__(self, key) -> dict:
        key = PairKey(*key) if not isinstance(key, PairKey) else key
        if self.geometry_on_device:
            return pair_to_sample(self.pair(key), None, None, key)
        last_error: Exception | None = None
        for attempt in range(4):
            pair = self.pair(key, attempt)
            try:
                source_geometry = compute_geometry(pair.source_network, self.geometry_config)
                target_geometry = compute_geometry(pair.target_network, self.geometry_config)
            except InvalidPointCloudError as error:  # degenerate draw: redraw
                last_error = error
                continue
            return pair_to_sample(pair, source_geometry, target_geometry, key)
        raise RuntimeError(f"{self.name} pair {key}: geometry failed 4 times") from last_error


def pair_to_sample(pair: Pair, source_geometry, target_geometry, key: PairKey | None = None) -> dict:
    """Flatten a pair and its two :class:`PointGeometry` into the dataset's sample dict.

    With ``source_geometry`` and ``target_geometry`` None the sample holds the network-frame
    points only (no ``*_edges`` / ``*_normals``): the geometry is computed on the device.
    """
    norm = pair.normalization
    if source_geometry is None or target_geometry is None:
        geometry = {
            "src_points": pair.source_network.astype(np.float32),
            "tgt_points": pair.target_network.astype(np.float32),
        }
    else:
        geometry = {
            "src_edges": source_geometry.edges,
            "src_points": source_geometry.points.astype(np.float32),
            "src_normals": source_geometry.normals.astype(np.float32),
            "tgt_edges": target_geometry.edges,
            "tgt_points": target_geometry.points.astype(np.float32),
            "tgt_normals": target_geometry.normals.astype(np.float32),
        }
    return {
        **geometry,
        "gt_match_src": pair.gt_match_src,
        "gt_match_tgt": pair.gt_match_tgt,
        "T_gt": pair.T_gt_network.astype(np.float32),
        "T_gt_user": pair.T_gt,
        "source_user": pair.source,
        "target_user": pair.target,
        "source_centre": np.asarray(norm.source_centre, dtype=np.float64),
        "target_centre": np.asarray(norm.target_centre, dtype=np.float64),
        "scale": np.float64(norm.scale),
        "protocol": pair.protocol,
        "epoch": -1 if key is None else int(key.epoch),
        "index": -1 if key is None else int(key.index),
    }


# ----------------------------------------------------------------------------- batching
class TrainBatchSampler(_TorchSampler):
    """Endless batches of :class:`PairKey` for training, resumable at any step.

    Epoch e visits the shapes in the order ``default_rng([seed, e, 2**32-1]).permutation(S)``
    (the extra word keeps this stream apart from the per-item streams), in ``S // B`` batches
    (the incomplete tail is dropped). Batch b of epoch e is global step
    ``e * (S // B) + b``; its protocol is the schedule's mix at that step evaluated at a
    uniform number drawn from the same epoch stream, so the sequence of batches depends only on
    the seed and not on where training was resumed.
    """

    def __init__(
        self,
        num_shapes: int,
        batch_size: int,
        schedule: ProtocolSchedule,
        seed: int = 0,
        start_step: int = 0,
    ) -> None:
        if batch_size < 1 or num_shapes < batch_size:
            raise ValueError(f"need 1 <= batch_size <= num_shapes, got {batch_size} and {num_shapes}")
        self.num_shapes = num_shapes
        self.batch_size = batch_size
        self.schedule = schedule
        self.seed = int(seed)
        self.start_step = int(start_step)

    @property
    def batches_per_epoch(self) -> int:
        return self.num_shapes // self.batch_size

    def epoch_plan(self, epoch: int) -> tuple[np.ndarray, np.ndarray]:
        """(shape order (S,), per-batch uniforms (batches_per_epoch,)) of an epoch."""
        rng = np.random.default_rng([self.seed, epoch, _SAMPLER_STREAM])
        return rng.permutation(self.num_shapes), rng.random(self.batches_per_epoch)

    def batch_keys(self, step: int) -> list[PairKey]:
        """The keys of global step ``step``."""
        epoch, batch = divmod(step, self.batches_per_epoch)
        order, uniforms = self.epoch_plan(epoch)
        return self._keys(epoch, batch, step, order, uniforms)

    def _keys(self, epoch, batch, step, order, uniforms) -> list[PairKey]:
        protocol = self.schedule.protocol_at(step, float(uniforms[batch]))
        points = self.schedule.points_at(step, protocol)
        indices = order[batch * self.batch_size : (batch + 1) * self.batch_size]
        return [PairKey(epoch, int(i), protocol, points) for i in indices]

    def __iter__(self) -> Iterator[list[PairKey]]:
        step = self.start_step
        while True:
            epoch, first_batch = divmod(step, self.batches_per_epoch)
            order, uniforms = self.epoch_plan(epoch)
            for batch in range(first_batch, self.batches_per_epoch):
                yield self._keys(epoch, batch, step, order, uniforms)
                step += 1


def validation_keys(
    num_shapes: int, num_pairs: int, mix: Mapping[str, float], seed: int = 0,
    points_per_cloud: int = SOURCE_POINTS, scan_points_per_cloud: int | None = None,
) -> list[PairKey]:
    """Fixed validation pairs: ``num_pairs`` shapes (cycled if fewer), protocols in proportion.

    Protocol counts follow ``mix`` exactly (largest remainders), assigned to the shapes by a
    seeded permutation; every key uses the reserved epoch ``VALIDATION_EPOCH`` (plus the cycle
    number when shapes repeat), so validation pairs never change during or across runs.
    """
    if num_pairs <= 0:
        return []
    rng = np.random.default_rng([seed, VALIDATION_EPOCH, _SAMPLER_STREAM])
    exact = {name: mix.get(name, 0.0) * num_pairs for name in PROTOCOLS}
    counts = {name: int(math.floor(value)) for name, value in exact.items()}
    for name in sorted(PROTOCOLS, key=lambda n: counts[n] - exact[n])[: num_pairs - sum(counts.values())]:
        counts[name] += 1
    protocols = [name for name in PROTOCOLS for _ in range(counts[name])]
    protocols = [protocols[i] for i in rng.permutation(num_pairs)]
    order = rng.permutation(num_shapes)
    keys = []
    for position, protocol in enumerate(protocols):
        cycle, slot = divmod(position, num_shapes)
        points = scan_points_per_cloud if protocol == SCAN_PROTOCOL and scan_points_per_cloud else points_per_cloud
        keys.append(PairKey(VALIDATION_EPOCH + cycle, int(order[slot]), protocol, points))
    return keys


def fixed_pair_batches(keys: Sequence[PairKey], batch_size: int) -> list[list[PairKey]]:
    """Group fixed keys into batches of one protocol and size (so they stack), order kept."""
    groups: dict[tuple[str, int], list[PairKey]] = {}
    for key in keys:
        groups.setdefault((key.protocol, key.points_per_cloud), []).append(key)
    batches = []
    for group in groups.values():
        batches.extend(group[i : i + batch_size] for i in range(0, len(group), batch_size))
    return batches
