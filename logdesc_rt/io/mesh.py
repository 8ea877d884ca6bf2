"""Meshes as registration input: read OBJ, STL, PLY, OFF and glTF, sample their surface.

A CAD model, a printer's STL or a reference mesh is registered to a scan as points sampled
uniformly on its surface (area-weighted: a large triangle gets proportionally more samples than
a small one, whatever the tessellation), seeded, so the same file gives the same points. The
pose the registration returns maps the mesh's own frame into the scan's, so
:meth:`Mesh.transformed` moves the mesh itself, faces and all (``--write-aligned``).

Reading and sampling go through trimesh (MIT, a well-kept mesh library), an optional extra:
``pip install "logdesc-rt[mesh]"``. Without it, a mesh-only file (OBJ, STL, glTF) raises a
:class:`~logdesc_rt.errors.PointCloudFileError` naming the extra, and a PLY / OFF with faces is
read as its vertices, as before.

Which files are meshes (:func:`read_registration_input`):
    OBJ, STL, GLB / glTF: always; their surface is sampled.
    PLY, OFF with a face element: their vertices are used, unless the caller asks for surface
        samples (``sample_surface=N``, ``--sample-surface N``) or the vertices are far too few
        or too uneven to stand for the surface at the working size (:func:`vertex_sampling_problem`);
        then the surface is sampled and ``notify`` says so.
    Anything else: a point cloud (:func:`~logdesc_rt.io.read_point_cloud`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import DEFAULT_WORKING_SIZE  # noqa: F401 (re-exported by logdesc_rt.io)
from ..errors import PointCloudFileError
from ..validation import as_points
from ._common import check_readable_file, file_error

MESH_ONLY_SUFFIXES: tuple[str, ...] = (".obj", ".stl", ".glb", ".gltf")
"""Suffixes that are always meshes (their surface is sampled)."""
FACE_SUFFIXES: tuple[str, ...] = (".ply", ".off")
"""Point-cloud suffixes that may carry faces."""
MESH_WRITE_SUFFIXES: tuple[str, ...] = (".ply", ".obj", ".stl", ".off", ".glb")
"""Suffixes :meth:`Mesh.write` writes (vertices and triangles)."""
DEFAULT_SURFACE_SAMPLES = 5000
"""Points sampled on a mesh's surface by default: several times any working size the bundled
model is run at (320 by default), so the working subset's farthest-point sampling picks from an
even, dense cover (the paper's femur case samples 5,000 points from its CAD model)."""
UNEVEN_TOP_VERTICES = 0.05
UNEVEN_AREA_SHARE = 0.25
"""A mesh's vertices are too uneven to stand for its surface when the 5 % of vertices that
stand for the most surface (a third of each triangle's area goes to each of its corners) stand
for more than 25 % of it. Even meshes are near 5-10 % (an icosphere 6 %, the Stanford Bunny's
reconstruction 8 %); a CAD model with long flat triangles beside fine curved detail is far above."""


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh in the file's units.

    Attributes:
        vertices: (V, 3) float64.
        faces: (F, 3) int64 vertex indices of the triangles, F >= 1.
        source: the file it was read from, or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    source: str | None = None

    @property
    def triangle_areas(self) -> np.ndarray:
        """(F,) float64 area of each triangle, in the file's units squared."""
        corners = self.vertices[self.faces]
        return 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)

    @property
    def area(self) -> float:
        """Total surface area, in the file's units squared."""
        return float(self.triangle_areas.sum())

    def sample(self, count: int = DEFAULT_SURFACE_SAMPLES, seed: int = 0) -> np.ndarray:
        """``count`` points drawn uniformly on the surface (area-weighted), seeded.

        Returns:
            (count, 3) float64, in the mesh's units; the same for the same mesh, count and seed.
        """
        if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
            raise ValueError(f"surface samples: {count!r} must be an integer >= 1")
        trimesh = _trimesh(None if self.source is None else Path(self.source))
        points, _ = trimesh.sample.sample_surface(self._trimesh(trimesh), int(count), seed=int(seed))
        return np.ascontiguousarray(points, dtype=np.float64)

    def transformed(self, transformation: np.ndarray) -> Mesh:
        """The mesh moved by a (4, 4) rigid transformation (faces unchanged)."""
        transformation = np.asarray(transformation, dtype=np.float64)
        moved = self.vertices @ transformation[:3, :3].T + transformation[:3, 3]
        return Mesh(moved, self.faces, self.source)

    def write(self, path: str | os.PathLike) -> None:
        """Write vertices and triangles (:data:`MESH_WRITE_SUFFIXES`, by suffix); vertex order kept."""
        path = Path(path)
        if path.suffix.lower() not in MESH_WRITE_SUFFIXES:
            raise file_error(
                path, f"cannot write a mesh as {path.suffix!r}; mesh formats: {', '.join(MESH_WRITE_SUFFIXES)}"
            )
        trimesh = _trimesh(path)
        try:
            self._trimesh(trimesh).export(path)
        except OSError as error:
            raise file_error(path, f"cannot write: {error.strerror or error}") from error

    def _trimesh(self, trimesh):
        # process=False: keep the vertices as given (no merging), so written files match.
        return trimesh.Trimesh(vertices=self.vertices, faces=self.faces, process=False)


def read_mesh(path: str | os.PathLike) -> Mesh:
    """Read the triangles of a mesh file (OBJ, STL, PLY, OFF, GLB / glTF; by suffix).

    Polygons are triangulated; a glTF scene's meshes are joined in the scene's frame.

    Raises:
        PointCloudFileError: missing / empty / unreadable file, content trimesh cannot parse,
            no faces, faces of zero total area, or trimesh not installed (the message names
            the extra). Coordinates that are not finite raise as for point clouds.
    """
    path = Path(path)
    check_readable_file(path)
    trimesh = _trimesh(path)
    if path.suffix.lower() == ".stl":
        _check_binary_stl_size(path)
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as error:
        raise file_error(path, f"cannot parse as {path.suffix.lower()[1:].upper()} mesh: {error}") from error
    faces = np.asarray(getattr(loaded, "faces", np.empty((0, 3))), dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        raise file_error(path, "no faces could be read from it (corrupt or truncated, or a mesh without faces), so "
                               "there is no surface to sample; for a point cloud, use PLY, XYZ, PCD or NPY")
    vertices = as_points(np.asarray(loaded.vertices, dtype=np.float64), name=str(path))
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise file_error(path, f"a face refers to a vertex beyond the {len(vertices)} vertices")
    mesh = Mesh(vertices, faces, os.fspath(path))
    if not mesh.area > 0:
        raise file_error(path, f"its {len(faces)} faces have zero total area")
    return mesh


def _check_binary_stl_size(path: Path) -> None:
    """A binary STL's size is fixed by its triangle count (84 + 50 bytes per triangle): name a
    truncated or padded file instead of trimesh's reading of it as an empty mesh."""
    with path.open("rb") as file:
        head = file.read(84)
    if head[:5].lower() == b"solid" or len(head) < 84:
        return  # ASCII STL (or too short to be binary): trimesh says what is wrong
    triangles = int.from_bytes(head[80:84], "little")
    expected, size = 84 + 50 * triangles, path.stat().st_size
    if size != expected:
        raise file_error(path, f"binary STL announces {triangles} triangles ({expected} bytes), the file has {size} "
                               "bytes: truncated or corrupt")


def sample_surface(mesh, count: int = DEFAULT_SURFACE_SAMPLES, seed: int = 0) -> np.ndarray:
    """``count`` seeded, area-weighted points on a mesh's surface.

    Args:
        mesh: a :class:`Mesh`, a mesh file's path, or a ``trimesh.Trimesh``.
        count: points to draw (>= 1).
        seed: the random seed; the same mesh, count and seed give the same points.

    Returns:
        (count, 3) float64 in the mesh's units.
    """
    return as_mesh(mesh).sample(count, seed)


def as_mesh(mesh) -> Mesh:
    """A :class:`Mesh` from a Mesh, a path, or a ``trimesh.Trimesh`` (looked up in ``sys.modules``,
    never imported here)."""
    if isinstance(mesh, Mesh):
        return mesh
    if isinstance(mesh, (str, os.PathLike)):
        return read_mesh(mesh)
    converted = trimesh_mesh(mesh)
    if converted is None:
        raise TypeError(f"expected a Mesh, a mesh file path or a trimesh.Trimesh, got {type(mesh).__name__}")
    return converted


def trimesh_mesh(value) -> Mesh | None:
    """A :class:`Mesh` of a ``trimesh.Trimesh``, or None for anything else."""
    import sys

    trimesh = sys.modules.get("trimesh")
    if trimesh is None or not isinstance(value, trimesh.Trimesh):
        return None
    faces = np.asarray(value.faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        raise ValueError("trimesh.Trimesh: has no faces, so there is no surface to sample")
    return Mesh(as_points(np.asarray(value.vertices, dtype=np.float64), name="trimesh vertices"), faces)


def vertex_sampling_problem(mesh: Mesh, working_size: int) -> str | None:
    """Why a mesh's vertices cannot stand for its surface at ``working_size`` points, or None.

    Far too few: fewer vertices than the working size (the network would see every vertex and
    still have gaps). Too uneven: see :data:`UNEVEN_AREA_SHARE`.
    """
    used = np.unique(mesh.faces)
    if len(used) < working_size:
        return f"only {len(used)} vertices on its faces, fewer than the working size of {working_size} points"
    share = np.bincount(
        mesh.faces.ravel(), weights=np.repeat(mesh.triangle_areas / 3.0, 3), minlength=len(mesh.vertices)
    )
    share = np.sort(share[used])[::-1]
    top = max(1, int(np.ceil(UNEVEN_TOP_VERTICES * len(share))))
    carried = float(share[:top].sum() / share.sum())
    if carried > UNEVEN_AREA_SHARE:
        return (f"its vertices are uneven: {UNEVEN_TOP_VERTICES:.0%} of them stand for {carried:.0%} of the surface "
                f"(over {UNEVEN_AREA_SHARE:.0%})")
    return None


def file_has_faces(path: Path) -> bool:
    """Whether a PLY or OFF file declares at least one face (its header only; no trimesh)."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".ply":
            from . import ply

            with path.open("rb") as file:
                face = ply.read_header(file).element("face")
            return face is not None and face.count > 0
        if suffix == ".off":
            from . import off

            return off.face_count(path) > 0
    except (OSError, ValueError):
        return False  # read_point_cloud reports what is wrong with the file
    return False


def is_mesh_file(path: str | os.PathLike) -> bool:
    """Whether a file is a mesh: a mesh-only suffix, or a PLY / OFF that declares faces."""
    path = Path(path)
    return path.suffix.lower() in MESH_ONLY_SUFFIXES or file_has_faces(path)


def read_registration_input(
    path: str | os.PathLike,
    *,
    sample_surface: int | None = None,
    working_size: int = DEFAULT_WORKING_SIZE,
    seed: int = 0,
    notify: Callable[[str], None] | None = None,
) -> tuple[np.ndarray, Mesh | None]:
    """The points to register from a file, and its mesh when it is one (see the module doc).

    Args:
        path: a point-cloud or mesh file.
        sample_surface: sample this many points on a mesh's surface (a PLY / OFF with faces
            included); None: :data:`DEFAULT_SURFACE_SAMPLES` for mesh-only formats, the
            vertices for a PLY / OFF unless :func:`vertex_sampling_problem` objects.
        working_size: the registration's working size, for that check.
        seed: the surface sampling's seed.
        notify: called with one line when a PLY / OFF is sampled on its surface without being
            asked, or could be but trimesh is missing (default: :func:`warnings.warn`).

    Returns:
        (points, mesh): (N, 3) float64 points and the Mesh (None for a point cloud).

    Raises:
        PointCloudFileError: as :func:`~logdesc_rt.io.read_point_cloud` and :func:`read_mesh`;
            ``sample_surface`` for a file without faces.
    """
    from . import read_point_cloud

    if notify is None:
        import warnings

        def notify(message: str) -> None:
            warnings.warn(message, stacklevel=3)

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in MESH_ONLY_SUFFIXES:
        mesh = read_mesh(path)
        return mesh.sample(sample_surface or DEFAULT_SURFACE_SAMPLES, seed), mesh
    has_faces = file_has_faces(path)
    if sample_surface is not None:
        if not has_faces:
            check_readable_file(path)
            raise file_error(path, f"has no faces, so its surface cannot be sampled (sample_surface={sample_surface})")
        mesh = read_mesh(path)
        return mesh.sample(sample_surface, seed), mesh
    points = read_point_cloud(path)
    if not has_faces:
        return points, None
    if not mesh_support_installed():
        if len(points) < working_size:
            notify(f"{path}: {len(points)} vertices and faces; its surface could be sampled instead: "
                   'pip install "logdesc-rt[mesh]"')
        return points, None
    mesh = read_mesh(path)
    problem = vertex_sampling_problem(mesh, working_size)
    if problem is None:
        return points, mesh
    notify(f"{path}: {problem}; using {DEFAULT_SURFACE_SAMPLES} points sampled on its surface instead "
           "(choose with sample_surface / --sample-surface N)")
    return mesh.sample(DEFAULT_SURFACE_SAMPLES, seed), mesh


def mesh_support_installed() -> bool:
    """Whether trimesh (the ``mesh`` extra) can be imported."""
    try:
        _trimesh()
    except PointCloudFileError:
        return False
    return True


def _trimesh(path: Path | None = None):
    try:
        import trimesh
    except ImportError as error:
        message = 'meshes need trimesh, which is not installed: pip install "logdesc-rt[mesh]"'
        raise (PointCloudFileError(message) if path is None else file_error(path, message)) from error
    return trimesh
