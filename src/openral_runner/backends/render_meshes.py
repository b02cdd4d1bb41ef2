"""Cheaper meshes for a software camera: vertex clustering of a MuJoCo model's render copy.

A CPU rasteriser (Mesa's llvmpipe) spends its time on vertices: the SO-101's CAD meshes have
about 320 000 triangles, and a 320×240 render of them costs ~70 ms, while the same scene with
every vertex snapped to a 2 mm grid (~24 000 triangles) renders in a quarter of that and differs
from it by well under one grey level per pixel on average. The camera is a stand-in for a real
one, so it needs the arm's silhouette and shading, not its fillets.

Vertex clustering (Rossignac and Borrel) is used because it is linear in the mesh size, needs no
manifold input (CAD exports are often not manifold) and never moves a vertex by more than one
cell: every vertex is replaced by the mean of the vertices in its grid cell, and triangles whose
corners fall into fewer than three cells disappear.

Only the *render copy* of a model is changed (the renderer's own ``MjModel``): its mesh arrays keep
their size, each simplified mesh is written at the start of its own ranges and its counts shrink.
Body and geom poses are untouched, so a simplified mesh stays exactly where the full one was.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def cluster_vertices(vertices: np.ndarray, faces: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Snap ``vertices`` to a grid of ``cell_m`` and keep the triangles that still span three cells.

    Args:
        vertices: ``(V, 3)`` positions in metres.
        faces: ``(F, 3)`` vertex indices, counter-clockwise seen from outside.
        cell_m: Grid cell edge in metres (> 0).

    Returns:
        ``(V', 3)`` float64 vertices (each the mean of one cell's vertices) and ``(F', 3)`` int32
        faces, orientation kept, without degenerate or repeated triangles; ``V' <= V``, ``F' <= F``.
    """
    if not cell_m > 0:
        raise ValueError(f"cell_m must be positive, got {cell_m}")
    points = np.asarray(vertices, dtype=np.float64)
    cells = np.floor(points / cell_m).astype(np.int64)
    _, cluster, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    cluster = cluster.reshape(-1)
    merged = np.zeros((len(counts), 3))
    np.add.at(merged, cluster, points)
    merged /= counts[:, None]
    snapped = cluster[np.asarray(faces)]
    a, b, c = snapped[:, 0], snapped[:, 1], snapped[:, 2]
    snapped = snapped[(a != b) & (b != c) & (a != c)]
    _, first = np.unique(np.sort(snapped, axis=1), axis=0, return_index=True)
    return merged, snapped[np.sort(first)].astype(np.int32)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normals per vertex: the area-weighted mean of the normals of the triangles around it."""
    corners = vertices[faces]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.zeros_like(vertices)
    for corner in range(3):
        np.add.at(normals, faces[:, corner], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    unit: np.ndarray = normals / np.maximum(length, 1e-12)
    return unit


def simplify_render_meshes(model: Any, cell_m: float) -> tuple[int, int]:
    """Replace every untextured mesh of ``model`` (a render copy) by its vertex clustering, in place.

    A textured mesh is kept whole (its texture coordinates would need clustering too), and so is
    one that clustering would not make smaller.

    Returns:
        The triangle count of the model's meshes before and after.
    """
    before = after = 0
    for mesh in range(int(model.nmesh)):
        vert_adr, vert_num = int(model.mesh_vertadr[mesh]), int(model.mesh_vertnum[mesh])
        face_adr, face_num = int(model.mesh_faceadr[mesh]), int(model.mesh_facenum[mesh])
        normal_adr, normal_num = int(model.mesh_normaladr[mesh]), int(model.mesh_normalnum[mesh])
        before += face_num
        if int(model.mesh_texcoordadr[mesh]) >= 0 or face_num == 0:
            after += face_num
            continue
        vertices, faces = cluster_vertices(
            model.mesh_vert[vert_adr : vert_adr + vert_num], model.mesh_face[face_adr : face_adr + face_num], cell_m
        )
        if len(faces) == 0 or len(faces) >= face_num or len(vertices) > normal_num:
            after += face_num
            continue
        model.mesh_vert[vert_adr : vert_adr + len(vertices)] = vertices
        model.mesh_vertnum[mesh] = len(vertices)
        model.mesh_normal[normal_adr : normal_adr + len(vertices)] = vertex_normals(vertices, faces)
        model.mesh_normalnum[mesh] = len(vertices)
        model.mesh_face[face_adr : face_adr + len(faces)] = faces
        model.mesh_facenormal[face_adr : face_adr + len(faces)] = faces
        model.mesh_facenum[mesh] = len(faces)
        after += len(faces)
    return before, after


__all__ = ["cluster_vertices", "simplify_render_meshes", "vertex_normals"]
