"""A batch of triangle meshes in packed form, with PyTorch3D's ``Meshes`` habits.

Connectivity (faces, edges, Laplacian, index maps) lives in an immutable topology object
that ``offset_verts`` / ``update_packed`` pass on unchanged, so a refinement stage only
swaps the vertex tensor. When every mesh has the same faces (the model's identical
ico-sphere per object), the topology keeps one face template and builds packed faces and
edges by broadcasting, with no Python loop over meshes.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from usl.geometry.topology import uniform_laplacian, unique_edges
from usl.utils.transfer import to_device

Tensor = torch.Tensor


def _counts(counts: list[int], device: torch.device) -> Tensor:
    """(B,) int64 ``counts`` on ``device``: filled there when all are equal (the shared topology),
    else copied over without a wait."""
    if counts and all(c == counts[0] for c in counts):
        return torch.full((len(counts),), counts[0], dtype=torch.int64, device=device)
    return to_device(counts, device, torch.int64)


class _Topology:
    """Per-batch connectivity; immutable once built, derived quantities cached lazily."""

    def __init__(self, faces_packed: Tensor, verts_counts: list[int], faces_counts: list[int], template: Tensor | None):
        device = faces_packed.device
        self.faces_packed = faces_packed
        self.verts_counts = verts_counts
        self.faces_counts = faces_counts
        self.template = template  # (F, 3) shared local faces, or None
        self.num_verts = _counts(verts_counts, device)
        self.num_faces = _counts(faces_counts, device)
        mesh_ids = torch.arange(len(verts_counts), device=device)
        # output sizes known on the host: no device read
        self.verts_to_mesh = torch.repeat_interleave(mesh_ids, self.num_verts, output_size=sum(verts_counts))
        self.faces_to_mesh = torch.repeat_interleave(mesh_ids, self.num_faces, output_size=sum(faces_counts))
        self.first_vert = torch.cumsum(self.num_verts, 0) - self.num_verts
        self._cache: dict[object, Tensor] = {}

    @classmethod
    def shared(cls, template: Tensor, num_meshes: int, num_verts: int, edges: Tensor | None = None) -> _Topology:
        offsets = torch.arange(num_meshes, device=template.device) * num_verts
        packed = (template.unsqueeze(0) + offsets[:, None, None]).reshape(-1, 3)
        topology = cls(packed, [num_verts] * num_meshes, [template.shape[0]] * num_meshes, template)
        if edges is not None:
            topology._cache["edges"] = topology._offset_template(edges)
        return topology

    def _offset_template(self, local: Tensor) -> Tensor:
        """The template's (E, 2) ``local`` vertex pairs in every mesh, packed."""
        return (local.unsqueeze(0) + self.first_vert[:, None, None]).reshape(-1, 2)

    def edges(self) -> Tensor:
        if "edges" not in self._cache:
            if self.template is not None:
                local = unique_edges(self.template, self.verts_counts[0] if self.verts_counts else None)
                self._cache["edges"] = self._offset_template(local)
            else:
                self._cache["edges"] = unique_edges(self.faces_packed, sum(self.verts_counts))
        return self._cache["edges"]

    def laplacian(self, dtype: torch.dtype) -> Tensor:
        key = ("laplacian", dtype)
        if key not in self._cache:
            self._cache[key] = uniform_laplacian(sum(self.verts_counts), self.edges(), dtype)
        return self._cache[key]

    def to(self, device: torch.device | str) -> _Topology:
        template = None if self.template is None else self.template.to(device)
        return _Topology(self.faces_packed.to(device), self.verts_counts, self.faces_counts, template)


class Meshes:
    """A batch of B triangle meshes of possibly different sizes, stored packed.

    Build with ``Meshes(verts_list, faces_list)`` (lists of (V_i, 3) float and (F_i, 3)
    integer tensors) or ``Meshes.from_shared_topology(verts (B, V, 3), faces (F, 3))``.
    Lists whose faces are all equal are detected and take the shared-topology path too.
    "Packed" tensors concatenate all meshes; packed faces index packed vertices.
    """

    def __init__(self, verts: Sequence[Tensor], faces: Sequence[Tensor]):
        if len(verts) != len(faces):
            raise ValueError(f"Meshes: got {len(verts)} vertex tensors but {len(faces)} face tensors")
        if len(verts) == 0:
            raise ValueError("Meshes: need at least one mesh (use from_shared_topology for an empty batch)")
        for i, (v, f) in enumerate(zip(verts, faces, strict=True)):
            _check_verts(v, i)
            _check_faces(f, v.shape[0], i)
        counts = [int(v.shape[0]) for v in verts]
        first = faces[0]
        if all(c == counts[0] for c in counts) and all(f is first or torch.equal(f, first) for f in faces):
            topology = _Topology.shared(first.long(), len(verts), counts[0])
        else:
            offsets = to_device([0] + counts[:-1], first.device).cumsum(0)
            sizes = to_device([f.shape[0] for f in faces], first.device)
            packed = torch.cat([f.long() for f in faces]) + torch.repeat_interleave(offsets, sizes)[:, None]
            topology = _Topology(packed, counts, [int(f.shape[0]) for f in faces], None)
        self._init(torch.cat(list(verts)), topology)

    @classmethod
    def from_shared_topology(cls, verts: Tensor, faces: Tensor, edges: Tensor | None = None) -> Meshes:
        """B meshes with one face template: verts (B, V, 3), faces (F, 3). No per-mesh loop.

        ``edges``: the template's ``unique_edges`` when the caller keeps them (``MeshTemplate``),
        which spares the device read of computing them.
        """
        if verts.dim() != 3 or verts.shape[-1] != 3 or not verts.is_floating_point():
            raise ValueError(
                f"Meshes.from_shared_topology: verts must be float (B, V, 3), got {verts.dtype} {tuple(verts.shape)}"
            )
        _check_faces(faces, verts.shape[1], "template", on_device=True)
        num_meshes, num_verts = verts.shape[:2]
        return cls._from_parts(verts.reshape(-1, 3), _Topology.shared(faces.long(), num_meshes, num_verts, edges))

    @classmethod
    def _from_parts(cls, verts_packed: Tensor, topology: _Topology) -> Meshes:
        meshes = cls.__new__(cls)
        meshes._init(verts_packed, topology)
        return meshes

    def _init(self, verts_packed: Tensor, topology: _Topology) -> None:
        self._verts_packed = verts_packed
        self._topology = topology

    # --- sizes and index maps -------------------------------------------------------
    def __len__(self) -> int:
        return len(self._topology.verts_counts)

    @property
    def device(self) -> torch.device:
        return self._verts_packed.device

    @property
    def dtype(self) -> torch.dtype:
        return self._verts_packed.dtype

    @property
    def shared_faces(self) -> Tensor | None:
        """The (F, 3) face template when all meshes share one topology, else None."""
        return self._topology.template

    def num_verts_per_mesh(self) -> Tensor:
        return self._topology.num_verts

    def num_faces_per_mesh(self) -> Tensor:
        return self._topology.num_faces

    def num_edges_per_mesh(self) -> Tensor:
        return torch.bincount(self.edges_packed_to_mesh_idx(), minlength=len(self))

    def verts_packed_to_mesh_idx(self) -> Tensor:
        return self._topology.verts_to_mesh

    def faces_packed_to_mesh_idx(self) -> Tensor:
        return self._topology.faces_to_mesh

    def edges_packed_to_mesh_idx(self) -> Tensor:
        return self._topology.verts_to_mesh[self.edges_packed()[:, 0]]

    def mesh_to_verts_packed_first_idx(self) -> Tensor:
        return self._topology.first_vert

    # --- geometry and connectivity ---------------------------------------------------
    def verts_packed(self) -> Tensor:
        """(sum V_i, 3) vertices of all meshes."""
        return self._verts_packed

    def faces_packed(self) -> Tensor:
        """(sum F_i, 3) int64 faces indexing ``verts_packed()``."""
        return self._topology.faces_packed

    def edges_packed(self) -> Tensor:
        """(sum E_i, 2) unique undirected edges indexing ``verts_packed()``, grouped by mesh."""
        return self._topology.edges()

    def laplacian_packed(self) -> Tensor:
        """Sparse (sum V_i, sum V_i) uniform Laplacian ``I - D^-1 A`` (see ``uniform_laplacian``)."""
        return self._topology.laplacian(self.dtype)

    def verts_list(self) -> list[Tensor]:
        return list(self._verts_packed.split(self._topology.verts_counts))

    def faces_list(self) -> list[Tensor]:
        """Per-mesh faces with local (per-mesh) vertex indices."""
        topo = self._topology
        if topo.template is not None:
            return [topo.template] * len(self)
        chunks = topo.faces_packed.split(topo.faces_counts)
        return [f - int(start) for f, start in zip(chunks, topo.first_vert.tolist(), strict=True)]

    def verts_padded(self) -> Tensor:
        """(B, max V_i, 3); a free view for shared topology, zero padded otherwise."""
        topo = self._topology
        if topo.template is not None:
            return self._verts_packed.view(len(self), topo.verts_counts[0], 3)
        return torch.nn.utils.rnn.pad_sequence(self.verts_list(), batch_first=True)

    # --- new meshes with the same topology --------------------------------------------
    def update_packed(self, new_verts_packed: Tensor) -> Meshes:
        """A new Meshes with these packed vertices and the same (shared, cached) topology."""
        if new_verts_packed.shape != self._verts_packed.shape:
            raise ValueError(
                f"Meshes.update_packed: expected verts of shape {tuple(self._verts_packed.shape)}, "
                f"got {tuple(new_verts_packed.shape)}"
            )
        return Meshes._from_parts(new_verts_packed, self._topology)

    def offset_verts(self, packed_offsets: Tensor) -> Meshes:
        """A new Meshes with ``verts_packed() + packed_offsets`` (differentiable)."""
        return self.update_packed(self._verts_packed + packed_offsets)

    def to(self, device: torch.device | str) -> Meshes:
        device = torch.device(device)
        if device == self.device and self._topology.faces_packed.device == device:
            return self
        return Meshes._from_parts(self._verts_packed.to(device), self._topology.to(device))

    def detach(self) -> Meshes:
        return Meshes._from_parts(self._verts_packed.detach(), self._topology)

    def __repr__(self) -> str:
        kind = "shared topology" if self.shared_faces is not None else "mixed topology"
        return f"Meshes({len(self)} meshes, {self._verts_packed.shape[0]} verts, {kind}, {self.device})"


def _check_faces(faces: Tensor, num_verts: int, which: object, on_device: bool = False) -> None:
    """``on_device``: the index range is asserted on the device (a RuntimeError, raised when the device
    gets there) rather than read back: the model's template is checked on every step."""
    if faces.dim() != 2 or faces.shape[1] != 3 or faces.is_floating_point():
        raise ValueError(
            f"Meshes: faces of mesh {which} must be an integer (F, 3) tensor, got {faces.dtype} {tuple(faces.shape)}"
        )
    if not faces.numel():
        return
    message = f"Meshes: faces of mesh {which} index outside its {num_verts} vertices"
    if on_device:
        torch._assert_async((faces.min() >= 0) & (faces.max() < num_verts), message)
    elif int(faces.min()) < 0 or int(faces.max()) >= num_verts:
        raise ValueError(message)


def _check_verts(verts: Tensor, which: object) -> None:
    if verts.dim() != 2 or verts.shape[1] != 3 or not verts.is_floating_point():
        raise ValueError(
            f"Meshes: verts of mesh {which} must be a float (V, 3) tensor, got {verts.dtype} {tuple(verts.shape)}"
        )
