"""Headless OpenGL renderer (moderngl over EGL: Mesa llvmpipe on CPU, or an NVIDIA driver).

One draw call per object writes, per pixel, linear RGB and the camera-frame depth ``z`` into a
single float32 RGBA target; the sign of ``z`` marks the tracked objects (``+z``) against the
rest of the scene (``-z``); 0 means nothing was drawn. One ``read`` per frame then gives RGB,
depth and mask together. A second, single-channel target holds each pixel's object label
(``k + 1`` for the tracked object ``k``, 0 for the static scene and for nothing), read by
:meth:`Renderer.labels` when several objects are tracked.

Conventions:
    * Camera: OpenCV (x right, y down, z forward), pinhole intrinsics of a
      :class:`~evtrack.PinholeCamera` (no distortion), pixel ``(u, v)`` centred at integer
      coordinates: the projection matrix maps ``u in [-0.5, W-0.5]`` onto the viewport.
    * The projection keeps OpenCV's y-down image rows in GL's bottom-up window rows, so the
      read-back buffer is already in image order (row 0 = top); no flip is needed.
    * Depth is the interpolated camera-frame ``z`` written by the fragment shader (exact at
      pixel centres for planar triangles), not the non-linear depth buffer.
    * Shading: ``albedo * (ambient + diffuse * max(0, n·l))`` with ``l`` towards the light in
      the camera frame; albedo = sRGB texture decoded to linear (``GL_SRGB8``) × vertex colour.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.sim.errors import GL_SYSTEM_PACKAGES, RendererUnavailableError
from evtrack.sim.objects import ObjectMesh

__all__ = ["Renderer", "RenderOutput", "gl_projection", "create_gl_context"]

_GL_SRGB8 = 0x8C41  # internal texture format: sRGB-encoded 8-bit RGB, sampled as linear

_VERTEX_SHADER = """
#version 330
uniform mat4 u_modelview;   // object -> camera (OpenCV frame)
uniform mat4 u_proj;        // camera -> clip
in vec3 in_pos;
in vec3 in_normal;
in vec2 in_uv;
in vec3 in_color;
out vec3 v_normal;
out vec2 v_uv;
out vec3 v_color;
out float v_z;
void main() {
    vec4 p = u_modelview * vec4(in_pos, 1.0);
    v_normal = mat3(u_modelview) * in_normal;
    v_uv = in_uv;
    v_color = in_color;
    v_z = p.z;
    gl_Position = u_proj * p;
}
"""

_FRAGMENT_SHADER = """
#version 330
uniform sampler2D u_texture;
uniform vec3 u_light;       // unit vector towards the light, camera frame
uniform float u_ambient;
uniform float u_diffuse;
uniform float u_sign;       // +1 tracked object, -1 everything else
uniform float u_label;      // k + 1 for tracked object k, 0 for the static scene
in vec3 v_normal;
in vec2 v_uv;
in vec3 v_color;
in float v_z;
layout(location = 0) out vec4 f_out;
layout(location = 1) out float f_label;
void main() {
    vec3 n = normalize(v_normal);
    float shade = u_ambient + u_diffuse * max(dot(n, u_light), 0.0);
    vec3 albedo = texture(u_texture, v_uv).rgb * v_color;
    f_out = vec4(albedo * shade, u_sign * v_z);
    f_label = u_label;
}
"""


def gl_projection(camera: PinholeCamera, near: float, far: float) -> np.ndarray:
    """The 4x4 projection from OpenCV camera coordinates to GL clip coordinates.

    ``x_ndc = 2 (u + 0.5) / W - 1`` and ``y_ndc = 2 (v + 0.5) / H - 1`` with ``(u, v)`` the
    pixel of :meth:`PinholeCamera.project` (so image row ``v`` is window row ``v`` from the
    bottom, i.e. the read-back buffer is in image order); ``z_ndc`` maps ``[near, far]`` onto
    ``[-1, 1]``; ``w_clip = z``.

    Returns:
        (4, 4) float64 matrix acting on column vectors.
    """
    if camera.dist is not None:
        raise ConfigError("the renderer is a pinhole: camera distortion must be None")
    if not 0 < near < far:
        raise ConfigError(f"render near/far must satisfy 0 < near < far, got {near}, {far}")
    w, h = camera.width, camera.height
    return np.array([
        [2.0 * camera.fx / w, 0.0, (2.0 * camera.cx + 1.0) / w - 1.0, 0.0],
        [0.0, 2.0 * camera.fy / h, (2.0 * camera.cy + 1.0) / h - 1.0, 0.0],
        [0.0, 0.0, (far + near) / (far - near), -2.0 * far * near / (far - near)],
        [0.0, 0.0, 1.0, 0.0],
    ])


def create_gl_context():
    """A standalone moderngl context on EGL; a clear error if the GL stack is missing."""
    try:
        import moderngl
    except ImportError as exc:  # pragma: no cover - moderngl is a dependency
        raise RendererUnavailableError(
            f"moderngl is not installed ({exc}); pip install moderngl") from exc
    try:
        return moderngl.create_standalone_context(backend="egl")
    except Exception as exc:
        raise RendererUnavailableError(
            "cannot create a headless OpenGL (EGL) context: "
            f"{type(exc).__name__}: {exc}. Install the system GL libraries, on Debian/Ubuntu: "
            f"sudo apt-get install -y {' '.join(GL_SYSTEM_PACKAGES)} "
            "(on NVIDIA machines the driver's libEGL_nvidia provides EGL)"
        ) from exc


@dataclass
class RenderOutput:
    """One rendered frame.

    Attributes:
        rgb: (H, W, 3) float32 linear RGB.
        depth: (H, W) float32 camera-frame z in metres, 0 where nothing was drawn.
        mask: (H, W) bool, pixels showing a tracked object.
    """

    rgb: np.ndarray
    depth: np.ndarray
    mask: np.ndarray


@dataclass
class _Drawable:
    vao: object
    texture: object
    buffers: tuple
    sign: float
    pose: np.ndarray | None  # None: takes the per-frame pose (the tracked object)
    lit: bool
    label: float = 0.0       # k + 1 for tracked object k


class Renderer:
    """Render textured objects (and a static scene) from a pinhole camera, headless.

    One object (:meth:`set_object`) or several (:meth:`set_objects`) are tracked: each is drawn
    at its own pose per frame; the static scene once.

    Args:
        camera: pinhole intrinsics and image size (no distortion).
        near, far: clipping distances, metres.
        light_direction: direction towards the light, camera frame (normalised here).
        ambient, diffuse: Lambertian shading terms.

    Example:
        >>> with Renderer(cam) as r:                                  # doctest: +SKIP
        ...     r.set_object(mesh)
        ...     out = r.render(T_object_to_camera)    # RenderOutput(rgb, depth, mask)
    """

    def __init__(
        self,
        camera: PinholeCamera,
        near: float = 0.05,
        far: float = 20.0,
        light_direction: tuple[float, float, float] = (-0.3, -0.5, -1.0),
        ambient: float = 0.35,
        diffuse: float = 0.65,
    ) -> None:
        import moderngl

        self.camera = camera
        self._proj = gl_projection(camera, near, far)
        self.ctx = create_gl_context()
        self._moderngl = moderngl
        self.program = self.ctx.program(vertex_shader=_VERTEX_SHADER,
                                        fragment_shader=_FRAGMENT_SHADER)
        self.program["u_proj"].write(self._proj.T.astype("f4").tobytes())
        self.program["u_texture"].value = 0
        self.set_light(light_direction, ambient, diffuse)
        size = (camera.width, camera.height)
        self._color = self.ctx.renderbuffer(size, 4, dtype="f4")
        self._label = self.ctx.renderbuffer(size, 1, dtype="f4")
        self._depth = self.ctx.depth_renderbuffer(size)
        self.fbo = self.ctx.framebuffer([self._color, self._label], self._depth)
        # the static scene is drawn once into its own framebuffer and copied in per frame
        self._static_color = self.ctx.renderbuffer(size, 4, dtype="f4")
        self._static_label = self.ctx.renderbuffer(size, 1, dtype="f4")
        self._static_depth = self.ctx.depth_renderbuffer(size)
        self._static_fbo = self.ctx.framebuffer([self._static_color, self._static_label],
                                                self._static_depth)
        self._static_dirty = True
        self._buffer = np.empty((camera.height, camera.width, 4), np.float32)
        self._label_buffer = np.empty((camera.height, camera.width), np.float32)
        self._objects: list[_Drawable] = []
        self._static: list[_Drawable] = []

    # ------------------------------------------------------------------ scene set-up
    def set_light(self, direction, ambient: float, diffuse: float) -> None:
        d = np.asarray(direction, np.float64)
        if not np.linalg.norm(d) > 0:
            raise ConfigError(f"light direction must be non-zero, got {direction}")
        self._light = (d / np.linalg.norm(d)).astype("f4")
        self._ambient, self._diffuse = float(ambient), float(diffuse)
        self._static_dirty = True

    def _drawable(self, mesh: ObjectMesh, sign: float, pose, lit: bool) -> _Drawable:
        with self.ctx:
            return self._make_drawable(mesh, sign, pose, lit)

    def _make_drawable(self, mesh: ObjectMesh, sign: float, pose, lit: bool) -> _Drawable:
        mgl = self._moderngl
        data = np.hstack([mesh.vertices, mesh.normals, mesh.uv, mesh.colors]).astype("f4")
        vbo = self.ctx.buffer(data.tobytes())
        ibo = self.ctx.buffer(np.ascontiguousarray(mesh.faces, "i4").tobytes())
        vao = self.ctx.vertex_array(
            self.program, [(vbo, "3f 3f 2f 3f", "in_pos", "in_normal", "in_uv", "in_color")],
            index_buffer=ibo, index_element_size=4)
        # image row 0 is the top; GL's texture row 0 is v = 0 (the bottom): flip on upload
        tex_img = np.ascontiguousarray(mesh.texture[::-1])
        tex = self.ctx.texture((tex_img.shape[1], tex_img.shape[0]), 3, tex_img.tobytes(),
                               internal_format=_GL_SRGB8)
        tex.build_mipmaps()
        tex.filter = (mgl.LINEAR_MIPMAP_LINEAR, mgl.LINEAR)
        tex.repeat_x = tex.repeat_y = True
        return _Drawable(vao, tex, (vbo, ibo), sign, None if pose is None
                         else np.asarray(pose, np.float64), lit)

    def set_object(self, mesh: ObjectMesh) -> None:
        """The tracked object (drawn at the pose passed to :meth:`render`)."""
        self.set_objects([mesh])

    def set_objects(self, meshes: list[ObjectMesh]) -> None:
        """Several tracked objects, object ``k`` labelled ``k + 1`` (drawn at the ``k``-th of
        the poses passed to :meth:`render_raw`)."""
        if not meshes:
            raise ConfigError("Renderer.set_objects: give at least one mesh")
        with self.ctx:
            for d in self._objects:
                self._release(d)
        self._objects = [self._drawable(m, 1.0, None, True) for m in meshes]
        for k, d in enumerate(self._objects):
            d.label = float(k + 1)

    def add_static(self, mesh: ObjectMesh, pose: np.ndarray, lit: bool = True) -> None:
        """A static part of the scene (background, distractor) at a fixed object->camera pose.

        Args:
            lit: shade it; unlit parts show their texture × vertex colour as is (emissive).
        """
        self._static.append(self._drawable(mesh, -1.0, pose, lit))
        self._static_dirty = True

    # ------------------------------------------------------------------ rendering
    def _draw(self, d: _Drawable, pose: np.ndarray) -> None:
        self.program["u_modelview"].write(np.asarray(pose, "f4").T.tobytes())
        self.program["u_sign"].value = d.sign
        self.program["u_label"].value = d.label
        self.program["u_light"].value = tuple(self._light)
        self.program["u_ambient"].value = self._ambient if d.lit else 1.0
        self.program["u_diffuse"].value = self._diffuse if d.lit else 0.0
        d.texture.use(0)
        d.vao.render()

    def render_raw(self, pose: np.ndarray | list[np.ndarray] | None) -> np.ndarray:
        """Render and return the internal (H, W, 4) float32 buffer ``(r, g, b, ±z)``.

        The buffer is reused by the next call; copy it to keep it. ``pose`` is the (4, 4)
        object-to-camera transform of the tracked object, or with several objects
        (:meth:`set_objects`) a list of one per object, or a (K, 4, 4) array (``None``: draw
        the static scene only). :meth:`labels` then gives which object each pixel shows.

        The renderer's GL context is made current for the call (and the one current before
        restored), so that several renderers can live in one thread.
        """
        with self.ctx:
            return self._render_raw(pose)

    def _render_raw(self, pose: np.ndarray | list[np.ndarray] | None) -> np.ndarray:
        mgl = self._moderngl
        if self._static_dirty:
            self._static_fbo.use()
            self.ctx.enable(mgl.DEPTH_TEST)
            self.ctx.disable(mgl.CULL_FACE)
            self._static_fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            for d in self._static:
                self._draw(d, d.pose)
            self._static_dirty = False
        self.ctx.copy_framebuffer(self.fbo, self._static_fbo)  # colour and depth
        self.fbo.use()
        self.ctx.enable(mgl.DEPTH_TEST)
        self.ctx.disable(mgl.CULL_FACE)
        if pose is not None:
            if not self._objects:
                raise RuntimeError("Renderer.render: call set_object first")
            poses = np.asarray(pose, np.float64).reshape(-1, 4, 4) if not isinstance(
                pose, list | tuple) else [np.asarray(p, np.float64) for p in pose]
            if len(poses) != len(self._objects):
                raise ValueError(f"{len(poses)} pose(s) for {len(self._objects)} object(s)")
            for d, p in zip(self._objects, poses, strict=True):
                if p.shape != (4, 4) or not np.isfinite(p).all():
                    raise ValueError(f"pose must be a finite (4, 4) matrix, got {p.shape}")
                self._draw(d, p)
        self.fbo.read_into(self._buffer, components=4, dtype="f4")
        return self._buffer

    def labels(self) -> np.ndarray:
        """(H, W) int16 object label of the last render: ``k + 1`` where tracked object ``k``
        shows, 0 elsewhere (static scene, nothing)."""
        with self.ctx:
            self.fbo.read_into(self._label_buffer, components=1, attachment=1, dtype="f4")
        return np.rint(self._label_buffer).astype(np.int16)

    def render(self, pose: np.ndarray | None) -> RenderOutput:
        """Render the scene with the tracked object at ``pose`` (object->camera, (4, 4))."""
        raw = self.render_raw(pose)
        return split_raw(raw)

    # ------------------------------------------------------------------ lifetime
    @staticmethod
    def _release(d: _Drawable) -> None:
        d.vao.release()
        d.texture.release()
        for b in d.buffers:
            b.release()

    def release(self) -> None:
        """Free the GL objects and the context (also done by ``with``)."""
        if self.ctx is None:
            return
        with self.ctx:
            for d in self._static + self._objects:
                self._release(d)
            self._static, self._objects = [], []
            for obj in (self.fbo, self._color, self._label, self._depth, self._static_fbo,
                        self._static_color, self._static_label, self._static_depth):
                obj.release()
            self.program.release()
        self.ctx.release()
        self.ctx = None

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def split_raw(raw: np.ndarray) -> RenderOutput:
    """Split a raw ``(r, g, b, ±z)`` buffer into :class:`RenderOutput` (copies)."""
    w = raw[..., 3]
    return RenderOutput(rgb=raw[..., :3].copy(), depth=np.abs(w), mask=w > 0)
