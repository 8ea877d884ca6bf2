"""Command line: ``logdesc-rt register | demo | describe | register-many | align``.

argparse and csv (standard library) are enough for five subcommands and keep the runtime's
dependencies at numpy, scipy, pykdtree and onnxruntime.

Everything that can be checked before the work is checked first (input files readable,
output folders and formats, matplotlib for ``--plot``, ``--config`` and ``--init`` files), so
a mistake costs no registration. Progress goes to stderr (``--quiet`` silences it); results
go to stdout.

Exit codes (``register`` and ``demo``):

    0  the registration succeeded (``success`` is true)
    2  an error: bad arguments, unreadable or invalid input, unwritable output
    3  the registration ran but is not a success (the pose is printed and written anyway);
       ``--allow-failure`` turns this into 0

``register-many``: 0 when every pair has a record that is ``ok`` and a ``success``; 3 when any
pair failed (error record) or is not a success; 2 for bad arguments or an unreadable pairs CSV
(nothing registered). ``align``: 0 when every scan is placed; 3 when any scan is disconnected
(poses.json is written anyway); 2 as above.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from ..config import DEFAULT_WORKING_SIZE, POSE_ESTIMATORS, REFINEMENT_METHODS
from ..errors import LogdescError
from ..metrics import rotation_error_deg

EXIT_OK = 0
EXIT_ERROR = 2
EXIT_NOT_SUCCESS = 3
PLOT_SUFFIXES = (".png", ".pdf", ".svg")
ESTIMATOR_HELP = (
    "auto (default): every candidate pose of the model's set (FSR, RANSAC, SVD, top-k and the "
    "consistency core for the bundled model) is verified on the full clouds and the best kept; fsr: the paper's "
    "farthest-sampling estimator; svd: confidence-weighted least squares on all matches; ransac: 3-point "
    "RANSAC; core: SVD on the largest mutually consistent set of matches. The chosen pose is always verified."
)
VIEW_HELP = ("write an interactive 3D page (one self-contained HTML file, opens offline in any browser): before / "
             "after, residual colours, matches; needs plotly (pip install 'logdesc-rt[plot]')")
SAMPLE_SURFACE_HELP = ("register meshes (OBJ, STL, GLB/glTF, and PLY/OFF with faces) as N points sampled on their "
                       "surface, area-weighted and seeded (default: 5000 for mesh formats; a PLY/OFF's vertices unless "
                       "they are too few or uneven); point clouds are used as they are")
EPILOG = f"""\
formats: PLY, PCD, XYZ/TXT/CSV (x y z in the first columns), NPY ((N, 3+) array), OFF; by suffix.
LAS/LAZ and E57 with the optional extras: pip install "logdesc-rt[las]" / "logdesc-rt[e57]".
meshes: OBJ, STL, GLB/glTF, PLY/OFF with faces (pip install "logdesc-rt[mesh]"), sampled on
their surface; --write-aligned OUT.ply/.obj/.stl/.off/.glb writes the moved mesh with its faces.

working size: clouds larger than the model's working size ({DEFAULT_WORKING_SIZE} points for the
bundled model) are subsampled to it (farthest-point sampling) for the networks; verification,
ICP, fitness and --write-aligned use the full clouds. The networks' memory grows with the square
of the working size (--max-points). --second-draw matches a pair the success flag does not claim
again on working subsets of the other subsampling method and keeps the more confident result.

success: the pose was verified on the full clouds and the calibrated confidence reached its
threshold (calibrated on validation pairs to be right, i.e. rotation error < 5 degrees and
translation error < 5 % of the radius, at least 95 % of the time when claimed;
benchmarks/results/success_calibration.md). The bundled network is invariant to rigid motion
by construction: relative rotations of any size are alike to it. Small overlaps, symmetric
shapes and sparse or differently sampled scans fail more often; the flag reports it.

exit codes: 0 success; 2 error (nothing registered); 3 registered but not a success
(--allow-failure: 0).
"""


class _Progress:
    """Timestamped progress lines on stderr (silent with --quiet)."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.start = time.perf_counter()

    def __call__(self, message: str) -> None:
        if not self.quiet:
            print(f"[{time.perf_counter() - self.start:6.1f} s] {message}", file=sys.stderr, flush=True)

    def warn(self, message: str) -> None:
        """A line the user must see even with --quiet (e.g. a mesh sampled without being asked)."""
        print(f"logdesc-rt: note: {message}", file=sys.stderr, flush=True)


def _version() -> str:
    from .. import __version__

    return __version__


# ----------------------------------------------------------------------------- checks before work
def _check_input(path: Path, what: str) -> None:
    from ..io import INPUT_SUFFIXES

    if path.suffix.lower() not in INPUT_SUFFIXES:
        raise ValueError(f"{what} {path}: unsupported suffix {path.suffix!r}; supported: {', '.join(INPUT_SUFFIXES)}")
    if not path.is_file():
        raise ValueError(f"{what} {path}: no such file")
    if not os.access(path, os.R_OK):
        raise ValueError(f"{what} {path}: not readable")
    _check_format_library(path, what)


def _check_format_library(path: Path, what: str) -> None:
    """LAS/LAZ/E57 need an optional library: say which extra to install, before the work."""
    from ..io import check_format_available

    try:
        check_format_available(path)
    except LogdescError as error:
        raise ValueError(f"{what}: {error}") from error


def _check_output(path: Path, what: str, suffixes: tuple[str, ...]) -> None:
    if path.suffix.lower() not in suffixes:
        raise ValueError(f"{what} {path}: unsupported suffix {path.suffix!r}; supported: {', '.join(suffixes)}")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise ValueError(f"{what} {path}: folder {folder} does not exist")
    if path.is_dir():
        raise ValueError(f"{what} {path}: is a folder")
    if not os.access(folder, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise ValueError(f"{what} {path}: not writable")


def _check_plot(path: Path | None) -> None:
    if path is None:
        return
    _check_output(path, "--plot", PLOT_SUFFIXES)
    try:
        import matplotlib  # noqa: F401
    except ImportError as error:
        raise ValueError("--plot needs matplotlib, which is not installed: pip install matplotlib "
                         "(or pip install 'logdesc-rt[plot]')") from error


def _check_view(path: Path | None) -> None:
    if path is None:
        return
    from .viewer import VIEW_SUFFIXES, check_view_available

    _check_output(path, "--view", VIEW_SUFFIXES)
    check_view_available(path)


def _check_sample_surface(sample_surface: int | None, paths: list[Path]) -> None:
    """--sample-surface names a count for meshes: an error when no input is one."""
    from ..io.mesh import is_mesh_file

    if sample_surface is not None and not any(is_mesh_file(path) for path in paths):
        raise ValueError(f"--sample-surface {sample_surface}: no input is a mesh (OBJ, STL, GLB/glTF, or a PLY/OFF "
                         "with faces); point clouds are registered as they are")


def _read_input(path: Path, sample_surface: int | None, working_size: int | None, progress) -> tuple:
    """(points, mesh or None) of an input file: ``--sample-surface`` applies to meshes only
    (mesh formats, PLY / OFF with faces); point clouds are used as they are."""
    from ..io import DEFAULT_WORKING_SIZE, read_registration_input
    from ..io.mesh import is_mesh_file

    is_mesh = is_mesh_file(path)
    points, mesh = read_registration_input(
        path, sample_surface=sample_surface if is_mesh else None, working_size=working_size or DEFAULT_WORKING_SIZE,
        notify=progress.warn,
    )
    sampled = mesh is not None and (sample_surface is not None or len(points) != len(mesh.vertices))
    if sampled:
        progress(f"{path}: a mesh of {len(mesh.faces)} triangles; {len(points)} points sampled on its surface")
    return points, mesh


def _read_init(path: Path) -> np.ndarray:
    """A (4, 4) initial guess from ..json (a 4x4 list, or {"transformation": ...} as --json
    prints), .npy, or whitespace-separated text."""
    from ..pose.evaluation import check_rigid_transformation

    if not path.is_file():
        raise ValueError(f"--init {path}: no such file")
    try:
        if path.suffix.lower() == ".json":
            value = json.loads(path.read_text())
            matrix = value["transformation"] if isinstance(value, dict) else value
        elif path.suffix.lower() == ".npy":
            matrix = np.load(path, allow_pickle=False)
        else:
            matrix = np.loadtxt(path, ndmin=2)
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise ValueError(f"--init {path}: cannot read a 4x4 matrix ({error})") from error
    return check_rigid_transformation(matrix, name=f"--init {path}")


def _runtime_config(args) -> dict:
    """--config FILE's partial RuntimeConfig dict ({} without it) with --second-draw applied,
    checked before any work; the Registrar applies it over the model's defaults (its
    manifest's "runtime")."""
    values = _config_file(args)
    if getattr(args, "second_draw", False):
        values.setdefault("subsampling", {})["second_draw"] = True
    return values


def _config_file(args) -> dict:
    """--config FILE's partial RuntimeConfig dict, checked ({} without it)."""
    from ..config import RuntimeConfig

    if getattr(args, "config", None) is None:
        return {}
    try:
        values = json.loads(Path(args.config).read_text())
    except OSError as error:
        raise ValueError(f"--config {args.config}: cannot read ({error.strerror or error})") from error
    except json.JSONDecodeError as error:
        raise ValueError(f"--config {args.config}: not JSON ({error})") from error
    try:
        RuntimeConfig.from_dict(values)  # unknown keys and bad values fail here, before loading
    except (ValueError, TypeError) as error:
        raise ValueError(f"--config {args.config}: {error}") from error
    return values


def _registrar(args, config=None):
    from ..registration import Registrar

    return Registrar(
        model_dir=args.model,
        threads=args.threads,
        max_points=args.max_points,
        subsampling=getattr(args, "subsampling", None),
        config=config,
    )


def _register_options(args) -> dict:
    refine = args.refine
    if refine == "none":
        refine = None
    options = {
        "estimator": args.estimator,
        "max_correspondence_distance": args.max_correspondence_distance,
        "seed": args.seed,
    }
    if args.refine is not None:
        options["refine"] = refine
    if getattr(args, "thorough", False):
        options["thorough"] = True
    return options


# ----------------------------------------------------------------------------- commands
def _format_matrix(matrix: np.ndarray) -> str:
    return "\n".join(" ".join(f"{value: .8f}" for value in row) for row in matrix)


def _summary_line(result) -> str:
    rmse = "n/a" if not np.isfinite(result.inlier_rmse) else f"{result.inlier_rmse:.4g}"
    verdict = "SUCCESS" if result.success else "NOT A SUCCESS"
    return (
        f"# {verdict}: confidence {result.confidence:.3f}, fitness {result.fitness:.3f}, inlier RMSE {rmse}, "
        f"{len(result.correspondences)} matches, pose from {result.pose_estimator}, "
        f"{result.timings['total']:.2f} s" + ("" if result.reason is None else f" ({result.reason})")
    )


def _command_register(args) -> int:
    from ..io import read_point_attributes, transform_attributes, writable_attributes, write_point_cloud

    progress = _Progress(args.quiet)
    # 1. Everything that can fail without registering.
    _check_input(args.source, "source")
    _check_input(args.target, "target")
    if args.write_aligned is not None:
        from ..io import MESH_WRITE_SUFFIXES, SUPPORTED_SUFFIXES
        from ..io.mesh import is_mesh_file

        # A mesh source is written as the moved mesh (faces and all) in a mesh format.
        writable = SUPPORTED_SUFFIXES + MESH_WRITE_SUFFIXES if is_mesh_file(args.source) else SUPPORTED_SUFFIXES
        _check_output(args.write_aligned, "--write-aligned", tuple(dict.fromkeys(writable)))
        if args.write_aligned.suffix.lower() in SUPPORTED_SUFFIXES:
            _check_format_library(args.write_aligned, "--write-aligned")
    _check_plot(args.plot)
    _check_view(args.view)
    _check_sample_surface(args.sample_surface, [args.source, args.target])
    config = _runtime_config(args)
    init = _read_init(args.init) if args.init is not None else None

    # 2. The work.
    progress(f"reading {args.source} and {args.target}")
    source, source_mesh = _read_input(args.source, args.sample_surface, args.max_points, progress)
    target, _ = _read_input(args.target, args.sample_surface, args.max_points, progress)
    attributes = read_point_attributes(args.source) if args.write_aligned is not None and source_mesh is None else {}
    progress(f"source {len(source)} points, target {len(target)} points; loading the model")
    registrar = _registrar(args, config)
    result = registrar.register(source, target, init=init, progress=progress, **_register_options(args))
    if args.write_aligned is not None and source_mesh is not None:
        _write_aligned_mesh(args.write_aligned, source_mesh, source, result, progress)
    elif args.write_aligned is not None:
        progress(f"writing the aligned source to {args.write_aligned}")
        moved_attributes = transform_attributes(attributes, result.rotation)
        kept = writable_attributes(args.write_aligned, moved_attributes)
        if len(kept) < len(moved_attributes):
            left_out = ", ".join(name for name in moved_attributes if name not in kept)
            progress(f"{args.write_aligned.suffix} has no place for attribute(s) {left_out}: left out")
        moved_attributes = kept
        write_point_cloud(args.write_aligned, source @ result.rotation.T + result.translation, moved_attributes)
    if args.plot is not None:
        from .plotting import plot_registration

        progress(f"drawing {args.plot}")
        plot_registration(source, target, result.transformation, args.plot, result=result)
    if args.view is not None:
        progress(f"writing the 3D view {args.view}")
        result.view(args.view, source, target)

    # 3. Results on stdout, verdict on stderr and in the exit code.
    if args.json:
        print(json.dumps(result.to_dict(), allow_nan=False))
    else:
        print(_format_matrix(result.transformation))
    print(_summary_line(result), file=sys.stderr)
    if not result.success:
        if args.allow_failure:
            return EXIT_OK
        print(
            f"logdesc-rt: the registration is not a success (confidence {result.confidence:.3f}); the pose was "
            f"printed anyway. Exit code {EXIT_NOT_SUCCESS}; --allow-failure exits 0.",
            file=sys.stderr,
        )
        return EXIT_NOT_SUCCESS
    return EXIT_OK


def _write_aligned_mesh(path: Path, mesh, samples: np.ndarray, result, progress) -> None:
    """The source mesh moved by the pose: the mesh with its faces in a mesh format, else the
    surface samples that were registered (a point-cloud format has no faces)."""
    from ..io import MESH_WRITE_SUFFIXES, write_point_cloud

    if path.suffix.lower() in MESH_WRITE_SUFFIXES:
        progress(f"writing the aligned mesh ({len(mesh.vertices)} vertices, {len(mesh.faces)} triangles) to {path}")
        mesh.transformed(result.transformation).write(path)
    else:
        progress(f"{path.suffix} holds points only: writing the {len(samples)} aligned surface samples to {path}")
        write_point_cloud(path, samples @ result.rotation.T + result.translation)


def _command_demo(args) -> int:
    from ..demo import make_demo_pair

    progress = _Progress(args.quiet)
    _check_plot(args.plot)
    _check_view(args.view)
    config = _runtime_config(args)
    pair = make_demo_pair()
    registrar = _registrar(args, config)
    result = registrar.register(pair.source, pair.target, progress=progress, **_register_options(args))
    truth = pair.true_transformation
    rotation_error = float(rotation_error_deg(result.rotation, truth[:3, :3]))
    translation_error = float(np.linalg.norm(result.translation - truth[:3, 3]))
    print("logdesc-rt demo: a generated table-with-bowl object, 768 of 1024 points per cloud,")
    print("known pose (up to 45 deg per axis, 0.5 translation), noise sigma 0.01, partial cuts.")
    print(f"model: {registrar.network.model_dir}")
    print("estimated transformation (source -> target):")
    print(_format_matrix(result.transformation))
    print("true transformation:")
    print(_format_matrix(truth))
    print(f"rotation error    {rotation_error:.3f} deg")
    print(f"translation error {translation_error:.4f} (object radius 1)")
    print(f"success {result.success} (confidence {result.confidence:.3f}), pose from {result.pose_estimator}")
    print(f"matches {len(result.correspondences)}, fitness {result.fitness:.3f}, inlier RMSE {result.inlier_rmse:.4f}")
    print("timings: " + ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in result.timings.items()))
    if args.plot:
        from .plotting import plot_registration

        progress(f"drawing {args.plot}")
        plot_registration(pair.source, pair.target, result.transformation, args.plot, result=result,
                          true_transformation=truth)
        print(f"picture written to {args.plot}")
    if args.view:
        result.view(args.view, pair.source, pair.target, true_transformation=truth)
        print(f"3D view written to {args.view} (open it in a browser)")
    if not result.success and not args.allow_failure:
        return EXIT_NOT_SUCCESS
    return EXIT_OK


def _command_describe(args) -> int:
    _check_input(args.cloud, "cloud")
    out = args.out or Path(args.cloud).with_suffix(".descriptors.npz")
    _check_output(Path(out), "--out", (".npz",))
    points, _ = _read_input(args.cloud, None, args.max_points, _Progress(quiet=True))
    described = _registrar(args).describe(points)
    np.savez(out, indices=described.indices, descriptors=described.descriptors, normals=described.normals,
             points=points[described.indices])
    print(f"{len(described.indices)} descriptors of dimension {described.descriptors.shape[1]} written to {out}")
    return EXIT_OK



# ----------------------------------------------------------------------------- many pairs, many scans
PAIRS_OUTPUT_SUFFIXES = (".jsonl", ".ndjson")


def _check_backend(args) -> None:
    """--backend ray needs Ray installed; --address only means something with Ray."""
    if args.backend == "ray":
        try:
            import ray  # noqa: F401
        except ImportError as error:
            raise ValueError(
                '--backend ray needs Ray, which is not installed: pip install "logdesc-rt[ray]"'
            ) from error
    elif args.address is not None:
        raise ValueError("--address is for --backend ray only")


def read_pairs_csv(path: Path) -> list[tuple[str, str, str]]:
    """The pairs of a CSV file: one ``source,target[,id]`` row per pair.

    A first row whose cells name the columns (``source``, ``target`` and optionally ``id``,
    any order, any case) is a header; otherwise the columns are source, target, id in that
    order. Blank rows and rows starting with ``#`` are skipped. Relative paths are resolved
    against the CSV file's folder, so the file can be moved with its clouds. The id defaults
    to ``"SOURCE -> TARGET"`` (paths as written in the file).

    Returns:
        (id, source path, target path) per pair, in file order.

    Raises:
        ValueError: the file is missing or unreadable, a row has the wrong number of cells or
            an empty path, ids repeat, or there are no pairs; the message names the row.
    """
    import csv

    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError as error:
        raise ValueError(f"pairs CSV {path}: no such file") from error
    except (OSError, UnicodeError) as error:
        raise ValueError(f"pairs CSV {path}: cannot read ({getattr(error, 'strerror', None) or error})") from error
    rows = [
        (number, [cell.strip() for cell in row])
        for number, row in enumerate(csv.reader(text.splitlines()), start=1)
        if row and any(cell.strip() for cell in row) and not row[0].lstrip().startswith("#")
    ]
    if not rows:
        raise ValueError(f"pairs CSV {path}: no pairs (expected rows 'source,target[,id]')")
    columns = {"source": 0, "target": 1, "id": 2}
    first = [cell.lower() for cell in rows[0][1]]
    if "source" in first and "target" in first:
        unknown = [cell for cell in first if cell not in columns]
        if unknown or len(set(first)) != len(first):
            raise ValueError(
                f"pairs CSV {path}: header {rows[0][1]} must name source, target and optionally id, once each"
            )
        columns = {name: first.index(name) for name in columns if name in first}
        rows = rows[1:]
        if not rows:
            raise ValueError(f"pairs CSV {path}: a header but no pairs")
    folder = path.parent
    needed = max(columns["source"], columns["target"]) + 1
    pairs: list[tuple[str, str, str]] = []
    seen: dict[str, int] = {}
    for number, cells in rows:
        if len(cells) not in (2, 3) or len(cells) < needed:
            raise ValueError(f"pairs CSV {path}, row {number}: {len(cells)} cells; expected source,target[,id]")
        source, target = cells[columns["source"]], cells[columns["target"]]
        if not source or not target:
            raise ValueError(f"pairs CSV {path}, row {number}: empty source or target path")
        given_id = cells[columns["id"]] if "id" in columns and columns["id"] < len(cells) else ""
        pair_id = given_id or f"{source} -> {target}"
        if pair_id in seen:
            raise ValueError(f"pairs CSV {path}, row {number}: pair id {pair_id!r} repeats row {seen[pair_id]}")
        seen[pair_id] = number
        pairs.append((pair_id, str(folder / source), str(folder / target)))
    return pairs


def _record_line(record: dict) -> str:
    if not record.get("ok"):
        return f"{record['id']}: ERROR {record['error']['type']}: {record['error']['message']}"
    verdict = "success" if record["success"] else "NOT A SUCCESS"
    return f"{record['id']}: {verdict}, confidence {record['confidence']:.3f}, fitness {record['fitness']:.3f}"


def _command_register_many(args) -> int:
    from ..batch import register_many

    progress = _Progress(args.quiet)
    # 1. Everything that can fail without registering.
    _check_output(args.out, "--out", PAIRS_OUTPUT_SUFFIXES)
    _check_backend(args)
    pairs = read_pairs_csv(args.pairs)
    config = _runtime_config(args)
    # The workers build their Registrar from the config: the working-size flags go into it.
    subsampling = {"max_points": args.max_points, "method": args.subsampling}
    subsampling = {key: value for key, value in subsampling.items() if value is not None}
    if subsampling:
        config = {**config, "subsampling": {**config.get("subsampling", {}), **subsampling}}

    # 2. The work: records stream to --out as pairs finish.
    bar = not args.quiet and sys.stderr.isatty()
    progress(f"{len(pairs)} pairs from {args.pairs}; records to {args.out}"
             + ("" if args.resume else " (started afresh: --no-resume)"))
    done = 0

    def report(record: dict) -> None:
        nonlocal done
        done += 1
        if not bar:
            progress(f"{done} done: {_record_line(record)}")

    records = register_many(
        [(pair_id, source, target) for pair_id, source, target in pairs],
        workers=args.workers,
        threads_per_worker=args.threads_per_worker,
        backend=args.backend,
        address=args.address,
        output=args.out,
        resume=args.resume,
        progress=False if args.quiet else (None if bar else False),
        on_record=report,
        model_dir=args.model,
        config=config,
        **_register_options(args),
    )

    # 3. Verdict: a summary on stdout, the failures named on stderr, the exit code.
    errors = [record for record in records if not record.get("ok")]
    not_success = [record for record in records if record.get("ok") and not record["success"]]
    skipped = len(records) - done
    print(f"{len(records)} pairs: {len(records) - len(errors) - len(not_success)} success, "
          f"{len(not_success)} not a success, {len(errors)} errors ({skipped} already in {args.out}, skipped)")
    for record in (errors + not_success)[:20]:
        print(f"logdesc-rt: {_record_line(record)}", file=sys.stderr)
    if errors or not_success:
        if args.allow_failure:
            return EXIT_OK
        print(f"logdesc-rt: {len(errors) + len(not_success)} of {len(records)} pairs failed or are not a success "
              f"(records in {args.out}). Exit code {EXIT_NOT_SUCCESS}; --allow-failure exits 0.", file=sys.stderr)
        return EXIT_NOT_SUCCESS
    return EXIT_OK


def _command_align(args) -> int:
    from ..align import AlignConfig, align, merge_scans

    progress = _Progress(args.quiet)
    # 1. Everything that can fail without registering.
    if len(args.scans) < 2:
        raise ValueError(f"align needs at least 2 scans, got {len(args.scans)}")
    for scan in args.scans:
        _check_input(scan, "scan")
    names = [str(scan) for scan in args.scans]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ValueError(f"scan {repeated[0]} is given more than once")
    _check_output(args.out, "--out", (".json",))
    if args.merged is not None:
        from ..io import ATTRIBUTE_SUFFIXES

        _check_output(args.merged, "--merged", ATTRIBUTE_SUFFIXES)
        _check_format_library(args.merged, "--merged")
    if args.voxel is not None and not (np.isfinite(args.voxel) and args.voxel > 0):
        raise ValueError(f"--voxel {args.voxel}: must be a positive length in the scans' unit")
    if args.pairs is not None:
        _check_output(args.pairs, "--pairs", PAIRS_OUTPUT_SUFFIXES)
    _check_plot(args.plot)
    _check_view(args.view)
    _check_sample_surface(args.sample_surface, list(args.scans))
    _check_backend(args)
    runtime_config = _runtime_config(args)
    refine = AlignConfig.refine if args.refine is None else (None if args.refine == "none" else args.refine)
    reference = None
    if args.reference is not None:  # the same file however its path is spelled
        resolved = [scan.resolve() for scan in args.scans]
        if args.reference.resolve() not in resolved:
            raise ValueError(f"--reference {args.reference}: not one of the scans given")
        reference = resolved.index(args.reference.resolve())
    config = AlignConfig(refine=refine, seed=0 if args.seed is None else args.seed, reference=reference)

    # 2. The work.
    progress(f"reading {len(names)} scans")
    scans = [_read_input(scan, args.sample_surface, None, progress)[0] for scan in args.scans]
    progress(f"aligning {len(names)} scans")
    result = align(
        scans,
        names=names,
        config=config,
        runtime_config=runtime_config,
        backend=args.backend,
        workers=args.workers,
        threads_per_worker=args.threads_per_worker,
        address=args.address,
        pairs_output=args.pairs,
        progress=False if args.quiet else None,
        model_dir=args.model,
    )
    progress(f"{result.candidate_pairs} pairs registered, {sum(edge.kept for edge in result.edges)} used; "
             f"poses in the frame of {result.reference}; writing {args.out}")
    args.out.write_text(json.dumps(result.to_json(), indent=1, allow_nan=False) + "\n")
    if args.merged is not None or args.plot is not None:
        points, scan = merge_scans(scans, result, args.voxel)
        if args.merged is not None:
            from ..io import write_point_cloud

            progress(f"writing the merged cloud ({len(points)} points) to {args.merged}")
            write_point_cloud(args.merged, points, attributes={"scan": scan})
        if args.plot is not None:
            from .plotting import plot_alignment

            progress(f"drawing {args.plot}")
            plot_alignment(points, scan, names, args.plot, disconnected=result.disconnected)
    if args.view is not None:
        progress(f"writing the 3D view {args.view}")
        result.view(args.view, scans)

    # 3. One line per scan on stdout, the verdict in the exit code.
    for name in names:
        verdict = "placed" if name in result.poses else "DISCONNECTED"
        print(f"{name}: {verdict}{' (reference)' if name == result.reference else ''}")
    if result.disconnected:
        if args.allow_failure:
            return EXIT_OK
        print(f"logdesc-rt: {len(result.disconnected)} of {len(names)} scans are disconnected (no verified pair ties "
              f"them to {result.reference}): {', '.join(result.disconnected)}. Exit code {EXIT_NOT_SUCCESS}; "
              "--allow-failure exits 0.", file=sys.stderr)
        return EXIT_NOT_SUCCESS
    return EXIT_OK


# ----------------------------------------------------------------------------- parser
def _count(minimum: int):
    """argparse type: an integer >= ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"{value} must be >= {minimum}")
        return value

    return parse


def _add_parallel_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workers", type=_count(0), default=None, metavar="N",
                        help="worker processes (local) or actors (ray); default: one per core; 0 runs in this process")
    parser.add_argument("--threads-per-worker", type=_count(1), default=None, metavar="T",
                        help="onnxruntime threads per worker (default: cores / workers)")
    parser.add_argument("--backend", choices=("local", "ray"), default="local",
                        help='local process pool (default) or a Ray cluster (pip install "logdesc-rt[ray]")')
    parser.add_argument("--address", default=None, metavar="ADDR",
                        help="Ray cluster to join, e.g. auto or ray://HEAD:10001 (default: a local Ray instance)")


def _add_runtime_options(parser: argparse.ArgumentParser, threads: bool = True) -> None:
    parser.add_argument("--model", type=Path, default=None, help="model directory (default: the bundled model)")
    if threads:
        parser.add_argument("--threads", type=int, default=None, help="onnxruntime threads (default: all cores)")
    parser.add_argument("--max-points", type=int, default=None,
                        help="working size per cloud for the networks "
                             f"(default: the model's, {DEFAULT_WORKING_SIZE} for "
                             "the bundled one); larger clouds are subsampled; memory grows with its square")


def _add_registration_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--estimator", choices=POSE_ESTIMATORS, default=None, help=ESTIMATOR_HELP)
    parser.add_argument("--refine", choices=("none", *REFINEMENT_METHODS), default=None,
                        help="ICP on the full clouds after the learned pose (default: none)")
    parser.add_argument("--max-correspondence-distance", type=float, default=None, metavar="D",
                        help="for ICP, fitness and inlier RMSE, in the clouds' unit "
                             "(default: 5%% of the larger radius)")
    parser.add_argument("--seed", type=int, default=None,
                        help="seeds every random choice (FSR, RANSAC, verification subsets); same input and seed, "
                             "same output (default 0)")
    parser.add_argument("--subsampling", choices=("fps", "voxel"), default=None,
                        help="how clouds above the working size are reduced (default fps: farthest-point)")
    parser.add_argument("--second-draw", action="store_true",
                        help="when the success flag does not claim the result, match the pair again on working "
                             "subsets of the other subsampling method and keep the more confident result (more "
                             "pairs registered; up to twice the time of the pairs the flag does not claim)")
    parser.add_argument("--config", type=Path, default=None, metavar="FILE.json",
                        help="runtime configuration (JSON, any subset of the 'config' object --json prints), "
                             "applied over the model's defaults (its manifest's \"runtime\"); the flags above "
                             "override it")
    parser.add_argument("--allow-failure", action="store_true",
                        help=f"exit 0 even when the result is not a success (default: exit {EXIT_NOT_SUCCESS})")
    parser.add_argument("--quiet", action="store_true", help="no progress messages on stderr")


def build_parser() -> argparse.ArgumentParser:
    from ..io import SUPPORTED_SUFFIXES

    formats = ", ".join(SUPPORTED_SUFFIXES)
    parser = argparse.ArgumentParser(
        prog="logdesc-rt",
        description="LoGDesc point-cloud registration on the CPU: estimates the rigid transform that maps "
                    "SOURCE onto TARGET, verifies it on the full clouds and says whether it is a success.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"logdesc-rt {_version()}")
    commands = parser.add_subparsers(dest="command", required=True)

    register = commands.add_parser(
        "register",
        help="register SOURCE onto TARGET, print the 4x4 transform",
        description="Estimate the rigid transform mapping SOURCE onto TARGET; print it (4x4, or --json).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    register.add_argument("source", type=Path, help=f"the cloud to move: a point-cloud file ({formats}), any unit")
    register.add_argument("--thorough", action="store_true",
                          help="verify every candidate pose, also when the fast exit is sure of the first one")
    register.add_argument("target", type=Path, help="the cloud to align it to, same unit")
    register.add_argument("--json", action="store_true",
                          help="print one JSON object: transformation (4x4 list), success, confidence, fitness, "
                               "inlier_rmse (null without inliers), correspondences, hypotheses, timings, config")
    register.add_argument("--write-aligned", type=Path, default=None, metavar="OUT",
                          help=f"write the moved source here ({formats}); a PLY input's normals (turned), colours "
                               "and other vertex properties are kept where the output format has room")
    register.add_argument("--plot", type=Path, default=None, metavar="OUT.png",
                          help="write a picture (before / after with residuals, correspondences); needs matplotlib")
    register.add_argument("--view", type=Path, default=None, metavar="OUT.html",
                          help=VIEW_HELP)
    register.add_argument("--sample-surface", type=_count(3), default=None, metavar="N",
                          help=SAMPLE_SURFACE_HELP)
    register.add_argument("--init", type=Path, default=None, metavar="FILE",
                          help="initial guess source -> target: a 4x4 matrix as text, .npy, or .json (a 4x4 list "
                               "or --json's output); verified with the other candidates")
    _add_registration_options(register)
    _add_runtime_options(register)
    register.set_defaults(handler=_command_register)

    demo = commands.add_parser("demo", help="register a generated example with known ground truth",
                               epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    demo.add_argument("--plot", type=Path, default=None, metavar="OUT.png",
                      help="write a picture (before / after, correspondences); needs matplotlib")
    demo.add_argument("--view", type=Path, default=None, metavar="OUT.html", help=VIEW_HELP)
    _add_registration_options(demo)
    _add_runtime_options(demo)
    demo.set_defaults(handler=_command_demo)

    describe = commands.add_parser("describe", help="write per-point learned descriptors of CLOUD (.npz)")
    describe.add_argument("cloud", type=Path, help=f"a point-cloud file ({formats})")
    describe.add_argument("--out", type=Path, default=None, help="output .npz (default: CLOUD.descriptors.npz)")
    _add_runtime_options(describe)
    describe.set_defaults(handler=_command_describe)

    many = commands.add_parser(
        "register-many",
        help="register every pair of a CSV file, records to JSON lines (resumable)",
        description="Register the pairs listed in PAIRS.csv (rows source,target[,id]; an optional header row names "
                    "the columns; relative paths are read from the CSV's folder) with one model load per worker. "
                    "One JSON record per pair is appended to --out as it finishes; a pair that fails becomes an "
                    "error record and the run goes on; pairs already done in --out are skipped.",
        epilog="exit codes: 0 every pair registered and a success; 3 any pair failed or is not a success "
               "(--allow-failure: 0); 2 bad arguments or unreadable CSV (nothing registered).",
    )
    many.add_argument("pairs", type=Path, metavar="PAIRS.csv", help="CSV: source,target[,id] per row")
    many.add_argument("--out", type=Path, required=True, metavar="RESULTS.jsonl",
                      help="JSON-lines output, one record per pair (appended; see logdesc_rt/batch.py for the keys)")
    many.add_argument("--no-resume", dest="resume", action="store_false",
                      help="start --out afresh instead of skipping the pairs already done in it")
    _add_parallel_options(many)
    _add_registration_options(many)
    _add_runtime_options(many, threads=False)
    many.set_defaults(handler=_command_register_many)

    align = commands.add_parser(
        "align",
        help="align a set of scans into one frame (pose graph)",
        description="Register candidate pairs of SCANs (all pairs up to 12 scans, else nearest scans by a global "
                    "descriptor), keep the verified ones, solve a pose graph and write each scan's 4x4 pose into "
                    "the reference scan's frame to --out (JSON: the reference, poses, the pairs used with their "
                    "residuals, disconnected scans). The reference is --reference, else the first scan of the "
                    "largest set the verified pairs connect (the first scan given, unless the pairs cut it off "
                    "from a larger set). Scans no verified pair ties to the reference are reported, never placed.",
        epilog="exit codes: 0 every scan placed; 3 some scan disconnected (--allow-failure: 0; poses.json is "
               "written anyway); 2 bad arguments, unreadable scan, unwritable output (nothing registered).",
    )
    align.add_argument("scans", type=Path, nargs="+", metavar="SCAN", help=f"two or more point-cloud files ({formats})")
    align.add_argument("--out", type=Path, required=True, metavar="POSES.json",
                       help='{"reference": scan, "poses": {scan: 4x4}, "pairs": [...], "disconnected": [...], ...}')
    align.add_argument("--reference", type=Path, default=None, metavar="SCAN",
                       help="the scan whose frame the poses are in, one of the SCANs (default: see above)")
    align.add_argument("--merged", type=Path, default=None, metavar="MERGED.ply",
                       help="write the aligned scans as one voxel-thinned cloud with a per-point 'scan' index")
    align.add_argument("--voxel", type=float, default=None, metavar="V",
                       help="voxel size of the merged cloud, in the scans' unit (default: 1/500 of its diagonal)")
    align.add_argument("--plot", type=Path, default=None, metavar="OVERVIEW.png",
                       help="write a picture of the merged cloud coloured by scan; needs matplotlib")
    align.add_argument("--view", type=Path, default=None, metavar="OUT.html",
                       help="write an interactive 3D page (each scan in its colour, the pairs used); needs plotly")
    align.add_argument("--sample-surface", type=_count(3), default=None, metavar="N", help=SAMPLE_SURFACE_HELP)
    align.add_argument("--pairs", type=Path, default=None, metavar="PAIRS.jsonl",
                       help="keep the pairwise records here (JSON lines); a rerun resumes from them")
    _add_parallel_options(align)
    align.add_argument("--refine", choices=("none", *REFINEMENT_METHODS), default=None,
                       help="ICP of each pair (default: point_to_plane)")
    align.add_argument("--seed", type=int, default=None, help="seeds registration (default 0)")
    align.add_argument("--config", type=Path, default=None, metavar="FILE.json",
                       help="runtime configuration of the pairwise registrations (JSON, as register --json prints)")
    align.add_argument("--allow-failure", action="store_true",
                       help=f"exit 0 even when some scan is disconnected (default: exit {EXIT_NOT_SUCCESS})")
    align.add_argument("--quiet", action="store_true", help="no progress messages on stderr")
    align.add_argument("--model", type=Path, default=None, help="model directory (default: the bundled model)")
    align.set_defaults(handler=_command_align)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.handler(args)
    except (LogdescError, ValueError, TypeError) as error:
        print(f"logdesc-rt: error: {error}", file=sys.stderr)
        return EXIT_ERROR


if __name__ == "__main__":
    sys.exit(main())
