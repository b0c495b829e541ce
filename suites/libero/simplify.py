"""Simplified copies of LIBERO's heavy visual meshes, for `render=fast`.

A LIBERO scene draws 300k+ mesh faces a view (libero_spatial's: 307k in 79 meshes; two scanned
bowls are 42k each), which llvmpipe rasterizes on the CPU. Each visual-only mesh (its geoms
collide with nothing and carry no inertia, so physics is unchanged) above a face cap is swapped
for a copy simplified by meshoptimizer's attribute-aware edge collapse. Why meshoptimizer: it
collapses an edge onto one of its own vertices, so every kept vertex keeps its exact position,
texture coordinates; vertices that share a position but not their texture
coordinates (a UV seam) only collapse along the seam, so textures do not smear across it.
(fast-simplification moves vertices and drops attributes: an earlier try lost the UVs, and the
images moved by 9.7/255 on average.)

The copy is made once per source file and cap, from the mesh as MuJoCo compiles it (so .obj,
.stl and .msh read alike), written back in the file's own frame as a MuJoCo .msh file, and
cached on disk under RETAIN_MESH_CACHE (default ~/.cache/retain/meshes), keyed by the source
file's bytes, the cap and SIMPLIFY_VERSION, written atomically. Deterministic: the same source
and cap give the same bytes.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from xml.etree import ElementTree

import numpy as np

SIMPLIFY_VERSION = 1  # bump when a cached copy would come out different
CACHE_ENV = "RETAIN_MESH_CACHE"
# texture coordinates count at full weight against the collapse's positional error (relative to
# the mesh's size)
UV_WEIGHT = 1.0
TARGET_ERROR = 1.0  # no error bound: the face cap decides


@dataclass(frozen=True)
class MeshData:
    """A mesh as flat per-vertex arrays (one vertex per distinct position and UV). No normals:
    MuJoCo computes them from the faces, as for a file without (closer to the source's images
    than its own normals averaged over a vertex's corners: 0.28/255 apart unsimplified, 0.38)."""

    vertices: np.ndarray  # [V, 3] float32, in the mesh file's frame
    texcoords: np.ndarray  # [V, 2] float32, or [0, 2] without texture coordinates
    faces: np.ndarray  # [F, 3] int32

    def to_msh(self) -> bytes:
        """MuJoCo's binary .msh: counts, then vertices, normals (none), texcoords and faces."""
        counts = np.array([len(self.vertices), 0, len(self.texcoords), len(self.faces)])
        return b"".join(a.astype(dtype).tobytes() for a, dtype in (
            (counts, "<i4"), (self.vertices, "<f4"), (self.texcoords, "<f4"),
            (self.faces, "<i4")))


def cache_dir() -> Path:
    return Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "retain" / "meshes")


def compiled_mesh(path: str) -> MeshData:
    """The mesh file as MuJoCo compiles it, moved back into the file's frame (MuJoCo centres a
    mesh on its centroid and turns it to its principal axes: mesh_pos and mesh_quat undo it)."""
    import mujoco

    xml = (f'<mujoco><asset><mesh name="m" file="{path}"/></asset><worldbody>'
           '<geom type="mesh" mesh="m" contype="0" conaffinity="0"/></worldbody></mujoco>')
    model = mujoco.MjModel.from_xml_string(xml)
    v0, nv = model.mesh_vertadr[0], model.mesh_vertnum[0]
    f0, nf = model.mesh_faceadr[0], model.mesh_facenum[0]
    t0, nt = model.mesh_texcoordadr[0], model.mesh_texcoordnum[0]
    rotation = np.zeros(9)
    mujoco.mju_quat2Mat(rotation, model.mesh_quat[0])
    rotation = rotation.reshape(3, 3)
    vertices = model.mesh_vert[v0:v0 + nv].astype(np.float64) @ rotation.T + model.mesh_pos[0]
    corners = [vertices[model.mesh_face[f0:f0 + nf]]]
    if t0 >= 0 and nt > 0:
        corners.append(model.mesh_texcoord[t0:t0 + nt][model.mesh_facetexcoord[f0:f0 + nf]])
    wedges = np.concatenate(corners, axis=2).astype(np.float32).reshape(3 * nf, -1)
    unique, inverse = np.unique(wedges, axis=0, return_inverse=True)  # sorted: deterministic
    texcoords = unique[:, 3:5] if unique.shape[1] > 3 else np.zeros((0, 2), np.float32)
    return MeshData(unique[:, 0:3], texcoords,
                    inverse.reshape(nf, 3).astype(np.int32))


def simplify(mesh: MeshData, max_faces: int) -> MeshData:
    """At most about `max_faces` faces (fewer where seams and borders allow no more collapses),
    its kept vertices unmoved, its unused vertices dropped."""
    textured = len(mesh.texcoords) > 0
    attributes = mesh.texcoords if textured else np.zeros((len(mesh.vertices), 1), np.float32)
    weights = np.array([UV_WEIGHT] * 2 if textured else [0.0], dtype=np.float32)
    positions = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    attributes = np.ascontiguousarray(attributes, dtype=np.float32)
    indices = np.ascontiguousarray(mesh.faces, dtype=np.uint32).ravel()
    out = np.zeros(len(indices), dtype=np.uint32)
    count = _simplify_with_attributes()(
        out.ctypes.data, indices.ctypes.data, len(indices), positions.ctypes.data,
        len(positions), positions.strides[0], attributes.ctypes.data, attributes.strides[0],
        weights.ctypes.data, len(weights), None, 3 * max_faces, TARGET_ERROR, 0, None)
    used, faces = np.unique(out[:count], return_inverse=True)
    return MeshData(mesh.vertices[used], mesh.texcoords[used] if textured else mesh.texcoords,
                    faces.reshape(-1, 3).astype(np.int32))


def _simplify_with_attributes():
    """meshoptimizer's C `meshopt_simplifyWithAttributes`, typed (the package's Python wrapper
    of it, 0.2.30a0, declares no argument types and cannot pass its float target error)."""
    import ctypes

    from meshoptimizer._loader import lib

    function = lib.meshopt_simplifyWithAttributes
    size, pointer = ctypes.c_size_t, ctypes.c_void_p
    function.argtypes = [pointer, pointer, size, pointer, size, size, pointer, size, pointer,
                         size, pointer, size, ctypes.c_float, ctypes.c_uint, pointer]
    function.restype = size
    return function


def simplified_file(source: str, max_faces: int) -> str | None:
    """The cached simplified copy of `source` (made now if missing), or None where MuJoCo's
    mesh has at most `max_faces` faces (drawn as it is)."""
    digest = hashlib.sha256(Path(source).read_bytes())
    digest.update(f"{max_faces}/{SIMPLIFY_VERSION}".encode())
    key = digest.hexdigest()[:20]
    directory = cache_dir()
    copy, keep = directory / f"{key}.msh", directory / f"{key}.keep"
    if copy.exists():
        return str(copy)
    if keep.exists():
        return None
    mesh = compiled_mesh(source)
    directory.mkdir(parents=True, exist_ok=True)
    if len(mesh.faces) <= max_faces:
        _write_atomic(keep, b"")
        return None
    _write_atomic(copy, simplify(mesh, max_faces).to_msh())
    return str(copy)


def _write_atomic(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def visual_meshes(root: ElementTree.Element) -> set[str]:
    """Meshes drawn only by geoms that collide with nothing and carry no inertia (group > 0;
    LIBERO's scenes count group 0 alone towards inertia): physics never reads them."""
    visual: dict[str, bool] = {}
    for geom in root.iter("geom"):
        mesh = geom.get("mesh")
        if mesh is None:
            continue
        drawn_only = (geom.get("contype") == "0" and geom.get("conaffinity") == "0"
                      and geom.get("group", "0") != "0")
        visual[mesh] = visual.get(mesh, True) and drawn_only
    return {name for name, only in visual.items() if only}


@dataclass(frozen=True)
class SimplifiedMeshes:
    """robosuite XML processor: each visual-only mesh file above `max_faces` faces swapped for
    its simplified copy (robosuite applies it at every reload)."""

    max_faces: int

    def __call__(self, xml: str) -> str:
        root = ElementTree.fromstring(xml)
        compiler = root.find("compiler")
        if compiler is None or compiler.get("inertiagrouprange") != "0 0":
            return xml  # not a scene whose visual geoms are known to carry no inertia
        visual = visual_meshes(root)
        for mesh in root.iter("mesh"):
            source = mesh.get("file")
            if source and mesh.get("name") in visual and os.path.isabs(source):
                copy = simplified_file(source, self.max_faces)
                if copy is not None:
                    mesh.set("file", copy)
        return ElementTree.tostring(root, encoding="unicode")


def simplified_meshes(max_faces: int) -> SimplifiedMeshes:
    return SimplifiedMeshes(max_faces)
