"""Planar objects: a textured rectangle, and one that fills a camera's view at a given depth.

A static planar scene seen by a moving camera (a poster, a wall, a table top) can be tracked as
an object: the plane is the object, its pose is the scene's pose relative to the camera, and
its twist is the scene's motion relative to the camera (the opposite of the camera's own).

Object frame of :func:`plane_mesh`: the plane lies in the object's ``z = 0`` plane, centred on
the origin, ``x`` along its width and ``y`` along its height. Its one face looks towards
``-z``: at the object-to-camera pose ``[I | (0, 0, d)]`` it stands ``d`` metres in front of a
camera (OpenCV axes, looking along ``+z``) and faces it, with the texture upright: the
texture's row 0 at ``y = -height/2`` (the camera's "up", since image ``y`` grows downwards)
and its column 0 at ``x = -width/2`` (image left).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.sim import textures
from evtrack.sim.objects import ObjectMesh

__all__ = ["plane_mesh", "view_plane_size", "plane_facing_camera", "facing_pose"]

_DEFAULT_TEXTURE_PX = 1024  # longer side of a generated or resampled texture


def plane_mesh(width_m: float, height_m: float, texture: np.ndarray | None = None, *,
               segments: tuple[int, int] = (1, 1), seed: int = 0,
               name: str = "plane") -> ObjectMesh:
    """A flat textured rectangle (see the module docstring for its frame and facing).

    Args:
        width_m, height_m: size along the object's ``x`` and ``y`` axes, metres (> 0).
        texture: (H, W, 3) or (H, W) uint8 image stretched over the whole face (row 0 at
            ``y = -height/2``); ``None``: a seeded room-like texture of the rectangle's aspect
            (:func:`evtrack.sim.textures.background_texture`), so that it makes events.
        segments: ``(nx, ny)`` cells of the vertex grid (>= 1 each). More cells only matter
            where vertices are projected one by one (a silhouette under lens distortion).
        seed: seed of the generated texture (ignored when ``texture`` is given).
        name: the mesh's name.

    Returns:
        An :class:`~evtrack.sim.objects.ObjectMesh` with ``(nx+1)(ny+1)`` vertices, all normals
        ``(0, 0, -1)``, faces counter-clockwise seen from ``-z``.

    Raises:
        ConfigError: a size that is not positive and finite, a bad ``segments`` or texture.

    Example:
        >>> m = plane_mesh(0.6, 0.4)
        >>> m.extents.round(3).tolist(), m.normals[0].tolist()
        ([0.6, 0.4, 0.0], [0.0, 0.0, -1.0])
    """
    w, h = float(width_m), float(height_m)
    if not (math.isfinite(w) and math.isfinite(h) and w > 0 and h > 0):
        raise ConfigError(f"plane size must be positive and finite, got {width_m} x {height_m} m")
    nx, ny = (int(s) for s in segments)
    if nx < 1 or ny < 1:
        raise ConfigError(f"plane segments must be >= 1 each, got {segments}")
    tex = _checked_texture(texture) if texture is not None else _generated_texture(w, h, seed)
    a = np.linspace(0.0, 1.0, nx + 1)
    b = np.linspace(0.0, 1.0, ny + 1)
    A, B = np.meshgrid(a, b)  # (ny+1, nx+1); B = 0 is the top row (y = -h/2)
    vertices = np.stack([(A - 0.5) * w, (B - 0.5) * h, np.zeros_like(A)], -1).reshape(-1, 3)
    uv = np.stack([A, 1.0 - B], -1).reshape(-1, 2)  # v grows upwards; texture row 0 at B = 0
    idx = np.arange((nx + 1) * (ny + 1)).reshape(ny + 1, nx + 1)
    top_left, top_right = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    bottom_left, bottom_right = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    # (b - a) x (c - a) along -z: a -> +x -> -y, i.e. bottom-left, bottom-right, top-right
    faces = np.concatenate([
        np.stack([bottom_left, bottom_right, top_right], -1),
        np.stack([bottom_left, top_right, top_left], -1),
    ])
    n = len(vertices)
    return ObjectMesh(
        name=name,
        vertices=vertices.astype(np.float32),
        faces=faces.astype(np.int32),
        normals=np.tile(np.array([0.0, 0.0, -1.0], np.float32), (n, 1)),
        uv=uv.astype(np.float32),
        texture=tex,
        colors=np.ones((n, 3), np.float32),
        source=f"procedural:plane:{w:.6g}x{h:.6g}m" + ("" if texture is not None
                                                      else f":seed={seed}"),
    )


def _checked_texture(texture: np.ndarray) -> np.ndarray:
    tex = np.asarray(texture)
    if tex.dtype != np.uint8 or tex.ndim not in (2, 3) or min(tex.shape[:2]) < 1:
        raise ConfigError(f"plane texture must be (H, W) or (H, W, 3) uint8, got "
                          f"{tex.shape} {tex.dtype}")
    if tex.ndim == 2:
        tex = np.repeat(tex[..., None], 3, axis=2)
    if tex.shape[2] != 3:
        raise ConfigError(f"plane texture must have 3 channels (RGB), got {tex.shape[2]}")
    return np.ascontiguousarray(tex)


def _generated_texture(w: float, h: float, seed: int) -> np.ndarray:
    long_px = _DEFAULT_TEXTURE_PX
    tw, th = (long_px, max(8, round(long_px * h / w))) if w >= h else (
        max(8, round(long_px * w / h)), long_px)
    return textures.background_texture(np.random.default_rng([seed, 7]), tw, th)


def facing_pose(depth_m: float) -> np.ndarray:
    """(4, 4) float64 object-to-camera pose ``[I | (0, 0, depth_m)]``: a :func:`plane_mesh`
    centred on the optical axis ``depth_m`` metres ahead, facing the camera."""
    T = np.eye(4)
    T[2, 3] = float(depth_m)
    return T


def view_plane_size(camera: PinholeCamera, depth_m: float, margin: float = 1.0
                    ) -> tuple[float, float]:
    """Width and height (metres) of a plane centred on the optical axis at ``depth_m`` that
    covers the camera's whole view, lens distortion undone, times ``margin``.

    The rays through the pixel corners along the image border (``-0.5`` and ``size - 0.5``)
    are undistorted; the plane spans twice the largest ``|x/z|`` and ``|y/z|``
    among them, so it stays in view when the camera turns or shifts a little (``margin`` > 1).

    Raises:
        ConfigError: a depth or margin that is not positive and finite.
    """
    d, m = float(depth_m), float(margin)
    if not (math.isfinite(d) and d > 0):
        raise ConfigError(f"plane depth must be positive and finite, got {depth_m} m")
    if not (math.isfinite(m) and m > 0):
        raise ConfigError(f"plane margin must be positive and finite, got {margin}")
    uv = _border_pixels(camera)
    ideal = camera.undistort_points(torch.from_numpy(uv)).numpy()
    xn = np.abs((ideal[:, 0] - camera.cx) / camera.fx).max()
    yn = np.abs((ideal[:, 1] - camera.cy) / camera.fy).max()
    return float(2.0 * xn * d * m), float(2.0 * yn * d * m)


def _border_pixels(camera: PinholeCamera) -> np.ndarray:
    """(2·(W+1) + 2·(H+1), 2) float64 points along the image's outer pixel edges, one per
    pixel corner."""
    w, h = camera.width - 0.5, camera.height - 0.5
    us, vs = np.arange(camera.width + 1) - 0.5, np.arange(camera.height + 1) - 0.5
    return np.concatenate([
        np.stack([us, np.full_like(us, -0.5)], -1), np.stack([us, np.full_like(us, h)], -1),
        np.stack([np.full_like(vs, -0.5), vs], -1), np.stack([np.full_like(vs, w), vs], -1),
    ])


def plane_facing_camera(camera: PinholeCamera, depth_m: float, *, margin: float = 1.5,
                        image: np.ndarray | None = None, image_pose: np.ndarray | None = None,
                        segments: tuple[int, int] = (8, 6), texture_px: int = _DEFAULT_TEXTURE_PX,
                        seed: int = 0, name: str = "plane") -> ObjectMesh:
    """A plane at :func:`facing_pose` ``(depth_m)`` covering ``camera``'s view (times
    ``margin``), optionally textured with what the camera saw of it.

    Args:
        camera: the camera (with its distortion, if any).
        depth_m: distance of the plane along the optical axis, metres.
        margin: the plane's size over the view's (see :func:`view_plane_size`).
        image: (H, W) or (H, W, 3) uint8, the camera's image (distorted, as recorded) of the
            plane, ``H, W`` the camera's size. Each texel takes the image's colour where its
            point projects; texels outside the image take the image's mean. ``None``: a
            generated texture (:func:`plane_mesh`).
        image_pose: (4, 4) object-to-camera pose at which ``image`` was taken (default
            :func:`facing_pose`), e.g. a frame taken a little after the pose the plane is
            placed at.
        segments: ``(nx, ny)`` cells of the vertex grid.
        texture_px: the longer side of the resampled texture, pixels.
        seed: seed of the generated texture when ``image`` is ``None``.
        name: the mesh's name.

    Raises:
        ConfigError: a bad depth, margin or image.
    """
    width, height = view_plane_size(camera, depth_m, margin)
    if image is None:
        return plane_mesh(width, height, segments=segments, seed=seed, name=name)
    img = _checked_texture(image)
    if img.shape[:2] != (camera.height, camera.width):
        raise ConfigError(f"plane image must be the camera's {camera.width}x{camera.height}, "
                          f"got {img.shape[1]}x{img.shape[0]}")
    pose = facing_pose(depth_m) if image_pose is None else np.asarray(image_pose, np.float64)
    tw, th = (texture_px, max(8, round(texture_px * height / width))) if width >= height else (
        max(8, round(texture_px * width / height)), texture_px)
    # texel centres -> object points -> camera points -> (distorted) pixels of the image
    x = (np.arange(tw) + 0.5) / tw * width - width / 2.0
    y = (np.arange(th) + 0.5) / th * height - height / 2.0
    X, Y = np.meshgrid(x, y)
    P = np.stack([X, Y, np.zeros_like(X)], -1).reshape(-1, 3) @ pose[:3, :3].T + pose[:3, 3]
    front = P[:, 2] > 1e-6
    uv = np.full((len(P), 2), -1e4)
    if front.any():
        uv[front] = camera.project(torch.from_numpy(P[front])).numpy()
    map_xy = uv.reshape(th, tw, 2).astype(np.float32)
    fill = tuple(float(c) for c in img.reshape(-1, 3).mean(0))
    texture = cv2.remap(img, map_xy[..., 0], map_xy[..., 1], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=fill)
    return plane_mesh(width, height, texture, segments=segments, name=name)
