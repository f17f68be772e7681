"""Offscreen rendering of an avatar with pyrender (EGL). The only module importing pyrender.

Speed on a CPU-only machine (Mesa llvmpipe) decides the design:

* **Lighting per vertex in numpy** (soft three-point light: a hemisphere ambient, a key light
  from upper left, a fill from the right, a faint rim), passed as vertex colours and drawn
  with pyrender's unlit (FLAT) shader. pyrender's PBR fragment shader costs ~70 ms per 720p
  frame on llvmpipe; the unlit one ~8 ms. With ~19k vertices Gouraud shading is smooth.
* **One dynamic vertex buffer**: per frame the deformed positions and lit colours are written
  into the existing GL buffer (``glBufferSubData``) instead of building a new ``pyrender.Mesh``.
* **Colour-only read-back**, no depth read, and 4x MSAA resolved by a blit (configurable:
  ``msaa``). The resolve turns the picture upside down, so the rows come back top-down as RGB
  and need no flip or channel copy in numpy (1080p: 3.4 ms a frame, against 4.2 ms for BGRA
  read back and re-ordered).
* **Only the avatar's rectangle is resolved**: the screen rectangle of the deformed vertices
  (joined with the previous frame's, so what that one left is replaced). Outside it the
  frame is the background either way - the pictures are the same bit for bit. Clearing and
  drawing are *not* limited to it: llvmpipe clears a whole framebuffer lazily, tile by tile,
  but a scissored clear writes every sample of the rectangle, and with a scissor box a
  1080p 4x-MSAA clip rendered slower (57 against 53 ms a frame; 720p 36-43 against 34-36).
* **One BLAS thread while rendering**: OpenBLAS's worker threads spin after every product
  (deforming, normals) and took a whole core from llvmpipe's rasterisers - 4x MSAA at 720p30
  ran at RTF 1.04 with them and 0.72 without (``facelab bench render``).
  :meth:`Renderer.frames` holds numpy's BLAS to one thread while a clip is drawn
  (:func:`facelab.blas_threads.one_blas_thread`).

Frames are ``(height, width, 3)`` uint8 RGB. ``PYOPENGL_PLATFORM`` defaults to ``egl``.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np
from scipy import sparse

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

if not hasattr(np, "infty"):  # pyrender 0.1.45 still uses the alias NumPy 2 removed
    np.infty = np.inf  # type: ignore[attr-defined]

import pyrender
from OpenGL import GL
from pyrender import renderer as _pr_renderer

from facelab.blas_threads import one_blas_thread
from facelab.errors import StageError
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.avatar.rig import HeadPose
from facelab.stimuli.render.scene import (
    AMBIENT,
    AMBIENT_UP,
    DEFAULT_DISTANCE_M,
    LIGHTS,
    RenderSettings,
    camera_placement,
)


def _count_egl_contexts() -> None:
    """Let several renderers be open at once in one process. pyrender's EGL platform
    terminates the process's one EGL display whenever any renderer is deleted (and destroys
    its context while still current): every other renderer still open is then left with a
    dead context, and its next GL call fails or touches freed driver memory. Here the display
    is terminated only when the last context goes, and a context is released before it is
    destroyed. Idempotent; nothing to do on other platforms (``PYOPENGL_PLATFORM`` not egl:
    the EGL module is not even imported, as importing it installs PyOpenGL's EGL platform)."""
    if os.environ.get("PYOPENGL_PLATFORM", "egl") != "egl":
        return
    try:
        from pyrender.platforms import egl as _egl
    except Exception:
        return
    cls = _egl.EGLPlatform
    if getattr(cls, "_facelab_counted", False):
        return
    # re-entrant: a renderer collected (pyrender's __del__) while another is being made or
    # closed on this thread comes back in here
    lock = threading.RLock()
    live: set[int] = set()
    init_context = cls.init_context

    def counted_init(self) -> None:  # type: ignore[no-untyped-def]
        with lock:  # not while another thread terminates the display
            init_context(self)
            live.add(id(self))

    def counted_delete(self) -> None:  # type: ignore[no-untyped-def]
        from OpenGL.EGL import (
            EGL_NO_CONTEXT,
            EGL_NO_SURFACE,
            eglDestroyContext,
            eglMakeCurrent,
            eglTerminate,
        )  # fmt: skip

        with lock:
            live.discard(id(self))
            last = not live
            if self._egl_display is None:
                return
            if self._egl_context is not None:
                eglMakeCurrent(self._egl_display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
                eglDestroyContext(self._egl_display, self._egl_context)
                self._egl_context = None
            if last:
                eglTerminate(self._egl_display)
            self._egl_display = None

    cls.init_context = counted_init
    cls.delete_context = counted_delete
    cls._facelab_counted = True


_count_egl_contexts()

__all__ = [
    "DEFAULT_DISTANCE_M",
    "FrameTimes",
    "NaiveRenderer",
    "RenderSettings",
    "Renderer",
    "look_at",
    "vertex_normals",
]


@dataclass
class FrameTimes:
    """Accumulated seconds per stage (for ``facelab bench render``)."""

    deform: float = 0.0
    shade: float = 0.0
    upload: float = 0.0
    raster_readback: float = 0.0
    frames: int = 0  # drawn
    repeated: int = 0  # shown again: the same weights and pose as the frame before

    def as_dict(self) -> dict[str, float]:
        """Milliseconds per frame of the clip (drawn or shown again)."""
        n = max(self.frames + self.repeated, 1)
        return {
            "deform_ms": 1000 * self.deform / n,
            "shade_ms": 1000 * self.shade / n,
            "upload_ms": 1000 * self.upload / n,
            "rasterize_and_readback_ms": 1000 * self.raster_readback / n,
        }


def vertex_normals(
    vertices: np.ndarray, faces: np.ndarray, incidence: sparse.csr_matrix | None = None
) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3), float32 (per frame, so written for speed:
    corner gathers with ``take`` and the cross product by components)."""
    v = vertices.astype(np.float32, copy=False)
    p0 = np.take(v, faces[:, 0], axis=0)
    e1 = np.take(v, faces[:, 1], axis=0) - p0
    e2 = np.take(v, faces[:, 2], axis=0) - p0
    fn = np.empty_like(e1)  # e1 x e2: twice the face's area along its normal
    fn[:, 0] = e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1]
    fn[:, 1] = e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2]
    fn[:, 2] = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    if incidence is None:
        incidence = _incidence(len(vertices), faces)
    vn = np.asarray(incidence @ fn, np.float32)
    length = np.sqrt(np.einsum("ij,ij->i", vn, vn))
    return vn / np.maximum(length, 1e-12)[:, None]


def _incidence(n_vertices: int, faces: np.ndarray) -> sparse.csr_matrix:
    rows = faces.reshape(-1)
    cols = np.repeat(np.arange(len(faces)), 3)
    return sparse.csr_matrix(
        (np.ones(len(rows), np.float32), (rows, cols)), shape=(n_vertices, len(faces))
    )


def look_at(
    eye: np.ndarray, target: np.ndarray, up: tuple[float, float, float] = (0.0, 1.0, 0.0)
) -> np.ndarray:
    """4x4 camera pose (OpenGL: the camera looks down its -z axis)."""
    f = target - eye
    f = f / np.linalg.norm(f)
    r = np.cross(f, np.asarray(up, dtype=float))
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = r, u, -f, eye
    return pose


_LIGHTS = tuple((np.array(d), i) for d, i in LIGHTS)  # shared with the live view
_WRAP = 0.25  # light wraps a little round the terminator, as it does on skin


def _shade(
    base_linear: np.ndarray, normals: np.ndarray, view_dir: np.ndarray, gloss: np.ndarray
) -> np.ndarray:
    """Soft lighting per vertex: hemisphere ambient (sky above, warm bounce below), wrapped
    Lambert key, fill and rim lights, and a Blinn-Phong highlight scaled by ``gloss``; sRGB.

    base_linear : (V, 3) linear-light base colours; normals : (V, 3) unit normals;
    gloss : (V,) specular strength.
    """
    dirs = np.stack([d / np.linalg.norm(d) for d, _ in _LIGHTS]).astype(np.float32)  # (L, 3)
    power = np.array([p for _, p in _LIGHTS], np.float32)
    lam = np.clip((normals @ dirs.T + _WRAP) / (1 + _WRAP), 0, None)  # (V, L)
    up = normals[:, 1]
    ambient = AMBIENT + AMBIENT_UP * up  # hemisphere: brighter from the sky than the ground
    light = ambient + lam @ power
    half = dirs[0] + view_dir.astype(np.float32)
    half /= np.linalg.norm(half)
    spec = (np.clip(normals @ half, 0, None) ** 28) * (0.10 * power[0]) * gloss
    lin = base_linear * light[:, None] + spec[:, None]
    return np.sqrt(np.clip(lin, 0, 1))  # ~ gamma 1/2 (display encoding)


_Box = tuple[int, int, int, int]  # x, y, width, height in GL window pixels (y up)


def _union(a: _Box, b: _Box) -> _Box:
    """The smallest rectangle holding both (an empty one - zero width or height - adds
    nothing)."""
    if a[2] <= 0 or a[3] <= 0:
        return b
    if b[2] <= 0 or b[3] <= 0:
        return a
    x0, y0 = min(a[0], b[0]), min(a[1], b[1])
    x1, y1 = max(a[0] + a[2], b[0] + b[2]), max(a[1] + a[3], b[1] + b[3])
    return (x0, y0, x1 - x0, y1 - y0)


@dataclass
class _Group:
    """The faces drawn with one material: their vertices, a pyrender primitive, its buffer."""

    vertices: np.ndarray  # (n,) indices into the avatar's vertices
    primitive: pyrender.Primitive
    interleaved: np.ndarray  # (n, 7) or (n, 9) float32: position, [uv], colour
    textured: bool


class Renderer:
    """Renders frames of one avatar. Use as a context manager (owns a GL context)."""

    def __init__(self, avatar: Avatar, settings: RenderSettings):
        self.avatar = avatar
        self.settings = settings
        self.times = FrameTimes()
        self._incidence = _incidence(len(avatar.neutral), avatar.faces)
        base = (
            avatar.colors
            if avatar.colors is not None
            else np.tile([0.8, 0.7, 0.65], (len(avatar.neutral), 1))
        )
        self._base = np.asarray(base, np.float32) ** 2  # linear light (gamma 2 approximation)
        self._gloss = (
            np.asarray(avatar.gloss, np.float32)
            if avatar.gloss is not None
            else np.full(len(avatar.neutral), 0.35, np.float32)
        )
        self._placement = camera_placement(avatar, settings)
        self._face_centre = self._placement.target
        self._view_dir = np.array([0.0, 0.0, 1.0])
        self._renderer: pyrender.OffscreenRenderer | None = None
        self._groups: list[_Group] = []

    def __enter__(self) -> Renderer:
        s = self.settings
        try:
            self._renderer = pyrender.OffscreenRenderer(s.width, s.height)
        except Exception as exc:  # EGL/driver problems surface as many exception types
            raise StageError(
                f"cannot open an offscreen OpenGL context (EGL): {exc}. "
                "Install libegl1 and libgl1-mesa-dri (scripts/setup.sh does)."
            ) from None
        max_samples = int(GL.glGetIntegerv(GL.GL_MAX_SAMPLES))
        if s.msaa > max(1, max_samples):
            gl_name = (GL.glGetString(GL.GL_RENDERER) or b"?").decode(errors="replace")
            self.__exit__()
            raise StageError(
                f"rendering.msaa is {s.msaa}, but this OpenGL "
                f"({gl_name}) multisamples at "
                f"most {max_samples} times: set rendering.msaa to "
                f"{' or '.join(str(v) for v in (1, 2, 4, 8) if v <= max(1, max_samples))}"
            )
        _use_fast_framebuffer(self._renderer._renderer, msaa=s.msaa)
        self._scene = pyrender.Scene(bg_color=[*s.background, 1.0], ambient_light=[1.0, 1.0, 1.0])
        self._groups = self._make_groups()
        self._scene.add(pyrender.Mesh([g.primitive for g in self._groups]))
        cam = self._placement
        eye = cam.eye
        self._view_dir = (eye - self._face_centre) / np.linalg.norm(eye - self._face_centre)
        self._camera = pyrender.PerspectiveCamera(
            yfov=np.radians(s.fov_deg), aspectRatio=s.width / s.height, znear=cam.near, zfar=cam.far
        )
        self._camera_pose = look_at(eye, self._face_centre)
        view_projection = self._camera.get_projection_matrix(s.width, s.height) @ np.linalg.inv(
            self._camera_pose
        )
        self._view_projection_rows = view_projection[[0, 1, 3]].astype(np.float32)
        self._scene.add(self._camera, pose=self._camera_pose)
        self._naive_scene: pyrender.Scene | None = None
        self._renderer._renderer._facelab_scissor(None)
        self._renderer.render(self._scene, flags=pyrender.RenderFlags.FLAT)  # binds the buffers
        return self

    def _make_groups(self) -> list[_Group]:
        a = self.avatar
        face_tex = a.face_texture if a.face_texture is not None else np.full(len(a.faces), -1)
        groups = []
        # cut-out and blended textures (the RGBA ones: see Avatar.textures) are drawn after the
        # opaque surfaces, blended, so what shows through them is already there
        used_tex = [int(t) for t in np.unique(face_tex)]
        see_through = {t for t in used_tex if t >= 0 and a.textures[t].shape[2] == 4}
        for tex in sorted(used_tex, key=lambda t: (t in see_through, t)):
            faces = a.faces[face_tex == tex]
            used, local = np.unique(faces, return_inverse=True)
            local = local.reshape(-1, 3).astype(np.int32)
            n = len(used)
            textured = tex >= 0 and a.uv is not None
            alpha = textured and tex in see_through
            material = pyrender.MetallicRoughnessMaterial(
                baseColorFactor=[1.0, 1.0, 1.0, 1.0],
                doubleSided=False,
                alphaMode="BLEND" if alpha else "OPAQUE",
                baseColorTexture=(
                    # glTF puts uv (0, 0) at the image's first row; GL at its last
                    pyrender.Texture(
                        source=np.flipud(a.textures[tex]).copy(),
                        source_channels="RGBA" if alpha else "RGB",
                    )
                    if textured
                    else None
                ),
            )
            prim = pyrender.Primitive(
                positions=a.neutral[used],
                indices=local,
                color_0=np.ones((n, 4), np.float32),
                texcoord_0=a.uv[used] if textured else None,
                material=material,
            )
            width = 9 if textured else 7
            inter = np.zeros((n, width), np.float32)
            if textured:
                inter[:, 3:5] = a.uv[used]
            inter[:, -1] = 1.0
            groups.append(_Group(used, prim, inter, textured))
        return groups

    @property
    def samples(self) -> int | None:
        """Samples per pixel the driver gave (``settings.msaa`` may be rounded up); None
        before the framebuffer exists."""
        if self._renderer is None:
            return None
        return getattr(self._renderer._renderer, "_facelab_samples", None)

    def __exit__(self, *exc: object) -> None:
        if self._renderer is not None:
            self._renderer.delete()
            self._renderer = None

    def _lit(self, verts: np.ndarray) -> np.ndarray:
        normals = vertex_normals(verts, self.avatar.faces, self._incidence)
        return _shade(self._base, normals, self._view_dir, self._gloss)

    def frame(self, weights: np.ndarray, *, pose: HeadPose | None = None) -> np.ndarray:
        """Render the avatar with target weights (K,) in ``avatar.target_names`` order, its
        head, neck and eyes turned by ``pose`` (needs a skeleton)."""
        verts, lit, box = self._prepare(weights, pose)
        self._upload(verts, lit)
        self._draw(box)
        return self._collect()

    def frames(
        self, weights: Iterable[np.ndarray], poses: Iterable[HeadPose | None] | None = None
    ) -> Iterator[np.ndarray]:
        """The frames of a clip, pipelined: while OpenGL (llvmpipe's threads) rasterises
        frame k, frame k + 1 is deformed and lit on the CPU. The same pictures as calling
        :meth:`frame` for each (weights, pose) pair; a frame whose weights and pose equal the
        frame before's (the still padding round the speech, an audio-only face) is that
        frame's picture again, not drawn twice (the same array object: copy it to keep it)."""
        pairs = (
            zip(weights, poses, strict=True) if poses is not None else ((w, None) for w in weights)
        )
        pending = False  # a frame drawn and not yet read back
        last: np.ndarray | None = None  # the last frame read back
        before: tuple[np.ndarray, HeadPose | None] | None = None  # what it was drawn from
        # one BLAS thread while the clip is drawn (see the module docstring); the caller's own
        # numpy work between clips (e.g. analysing the next stimulus) keeps its threads
        with one_blas_thread():
            for w, pose in pairs:
                if before is not None and pose == before[1] and np.array_equal(w, before[0]):
                    if pending:
                        last, pending = self._collect(), False
                        yield last
                    self.times.repeated += 1
                    yield last
                    continue
                prepared = self._prepare(w, pose)  # overlaps the previous frame's rasterisation
                if pending:
                    last = self._collect()
                    yield last
                verts, lit, box = prepared
                self._upload(verts, lit)
                self._draw(box)
                pending, before = True, (np.array(w, copy=True), pose)
        if pending:
            yield self._collect()

    def _prepare(
        self, weights: np.ndarray, pose: HeadPose | None
    ) -> tuple[np.ndarray, np.ndarray, _Box | None]:
        """Deformed vertices, their lit colours and their screen rectangle (CPU)."""
        t0 = time.perf_counter()
        verts = self.avatar.deform(weights, pose=pose)
        t1 = time.perf_counter()
        lit = self._lit(verts)
        self.times.deform += t1 - t0
        self.times.shade += time.perf_counter() - t1
        return verts, lit, self._screen_box(verts)

    def _screen_box(self, verts: np.ndarray) -> _Box | None:
        """The window rectangle (x, y, width, height; GL pixels, y up from the bottom row)
        holding the projection of every vertex, with a 2-pixel margin, clipped to the frame;
        None (the whole frame) when a vertex lies behind the camera. A triangle's pixels lie
        within its corners' rectangle, so nothing drawn falls outside (``verts`` (V, 3), m).
        """
        s = self.settings
        vp = self._view_projection_rows  # (3, 4) float32: the x, y and w rows
        hom = verts @ vp[:, :3].T + vp[:, 3]  # (V, 3)
        w = hom[:, 2]
        if not len(w) or w.min() <= 1e-6:
            return None
        x = hom[:, 0] / w
        y = hom[:, 1] / w
        x = (np.array([x.min(), x.max()], float) + 1) / 2 * s.width
        y = (np.array([y.min(), y.max()], float) + 1) / 2 * s.height
        x0 = int(np.clip(np.floor(x.min()) - 2, 0, s.width))
        x1 = int(np.clip(np.ceil(x.max()) + 2, 0, s.width))
        y0 = int(np.clip(np.floor(y.min()) - 2, 0, s.height))
        y1 = int(np.clip(np.ceil(y.max()) + 2, 0, s.height))
        return (x0, y0, max(0, x1 - x0), max(0, y1 - y0))

    def _upload(self, verts: np.ndarray, lit: np.ndarray) -> None:
        t0 = time.perf_counter()
        assert self._renderer is not None
        self._renderer._platform.make_current()  # another renderer may have drawn since
        if not self._groups[0].primitive._buffers:  # another scene was drawn since
            self._renderer._renderer._facelab_scissor(None)
            self._renderer.render(self._scene, flags=pyrender.RenderFlags.FLAT)
        for g in self._groups:
            g.interleaved[:, :3] = verts[g.vertices]
            g.interleaved[:, -4:-1] = lit[g.vertices]
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, g.primitive._buffers[0])
            GL.glBufferSubData(GL.GL_ARRAY_BUFFER, 0, g.interleaved.nbytes, g.interleaved)
        self.times.upload += time.perf_counter() - t0

    def _draw(self, box: _Box | None) -> None:
        """Issue the frame's drawing, limited to ``box`` (see :meth:`_screen_box`; None: the
        whole frame), and let the rasteriser start (no read-back yet)."""
        t0 = time.perf_counter()
        assert self._renderer is not None
        gl = self._renderer._renderer
        gl._facelab_scissor(box)
        gl._facelab_defer_read = True
        try:
            self._renderer.render(self._scene, flags=pyrender.RenderFlags.FLAT)
        finally:
            gl._facelab_defer_read = False
        self.times.raster_readback += time.perf_counter() - t0

    def _collect(self) -> np.ndarray:
        """The drawn frame, read back (waits for the rasteriser)."""
        t0 = time.perf_counter()
        assert self._renderer is not None
        self._renderer._platform.make_current()
        color = self._renderer._renderer._facelab_read()
        self.times.raster_readback += time.perf_counter() - t0
        self.times.frames += 1
        return color

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) as (column, row) of world points (N, 3) in rendered frames."""
        s = self.settings
        proj = self._camera.get_projection_matrix(s.width, s.height)
        view = np.linalg.inv(self._camera_pose)
        hom = np.column_stack([points, np.ones(len(points))]) @ (proj @ view).T
        ndc = hom[:, :2] / hom[:, 3:4]
        return np.column_stack([(ndc[:, 0] + 1) / 2 * s.width, (1 - ndc[:, 1]) / 2 * s.height])

    def frame_rebuild(self, weights: np.ndarray) -> np.ndarray:
        """Same shading, but a new ``pyrender.Mesh`` per frame (isolates the rebuild cost)."""
        verts = self.avatar.deform(weights)
        lit = self._lit(verts)
        prim = pyrender.Primitive(
            positions=verts,
            indices=self.avatar.faces,
            color_0=np.column_stack([lit, np.ones(len(lit))]).astype(np.float32),
            material=pyrender.MetallicRoughnessMaterial(doubleSided=False),
        )
        if self._naive_scene is None:
            s = self.settings
            self._naive_scene = pyrender.Scene(
                bg_color=[*s.background, 1.0], ambient_light=[1.0, 1.0, 1.0]
            )
            self._naive_scene.add(self._camera, pose=self._camera_pose)
        node = self._naive_scene.add(pyrender.Mesh([prim]))
        assert self._renderer is not None
        self._renderer._renderer._facelab_scissor(None)
        color = self._renderer.render(self._naive_scene, flags=pyrender.RenderFlags.FLAT)[0]
        self._naive_scene.remove_node(node)
        return color


class NaiveRenderer:
    """The straightforward pyrender loop, as a baseline for ``facelab bench render``: per
    frame a ``trimesh.Trimesh`` -> ``pyrender.Mesh.from_trimesh`` rebuilt and added to the
    scene, pyrender's default lit (PBR) shading with a directional light, default
    framebuffer (4x MSAA, colour and depth read back)."""

    def __init__(self, avatar: Avatar, settings: RenderSettings, *, camera_pose: np.ndarray):
        import trimesh

        self._trimesh = trimesh
        self.avatar = avatar
        s = settings
        self._renderer = pyrender.OffscreenRenderer(s.width, s.height)
        self._scene = pyrender.Scene(bg_color=[*s.background, 1.0], ambient_light=[0.3, 0.3, 0.3])
        cam = pyrender.PerspectiveCamera(
            yfov=np.radians(s.fov_deg), aspectRatio=s.width / s.height, znear=0.05, zfar=5.0
        )
        self._scene.add(cam, pose=camera_pose)
        self._scene.add(pyrender.DirectionalLight(intensity=3.0), pose=camera_pose)
        self._colors = (
            (np.clip(avatar.colors, 0, 1) * 255).astype(np.uint8)
            if avatar.colors is not None
            else None
        )

    def frame(self, weights: np.ndarray) -> np.ndarray:
        verts = self.avatar.deform(weights)
        mesh = self._trimesh.Trimesh(
            verts, self.avatar.faces, vertex_colors=self._colors, process=False
        )
        node = self._scene.add(pyrender.Mesh.from_trimesh(mesh, smooth=True))
        color, _depth = self._renderer.render(self._scene)
        self._scene.remove_node(node)
        return color

    def close(self) -> None:
        self._renderer.delete()


def _use_fast_framebuffer(renderer: _pr_renderer.Renderer, *, msaa: int) -> None:
    """Replace pyrender's framebuffer handling on this renderer: colour-only RGB read-back of
    the resolved (and upside-down) picture."""

    def configure(self: _pr_renderer.Renderer) -> None:
        if self._main_fb is not None:
            return
        w, h = self.viewport_width, self.viewport_height
        cb, db = GL.glGenRenderbuffers(2)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, cb)
        if msaa > 1:
            GL.glRenderbufferStorageMultisample(GL.GL_RENDERBUFFER, msaa, GL.GL_RGBA8, w, h)
        else:
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA8, w, h)
        # the driver may round the request up (llvmpipe gives 4 for 2)
        self._facelab_samples = max(
            1, int(GL.glGetRenderbufferParameteriv(GL.GL_RENDERBUFFER, GL.GL_RENDERBUFFER_SAMPLES))
        )
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, db)
        if msaa > 1:
            GL.glRenderbufferStorageMultisample(
                GL.GL_RENDERBUFFER, msaa, GL.GL_DEPTH_COMPONENT24, w, h
            )
        else:
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT24, w, h)
        fb = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, fb)
        GL.glFramebufferRenderbuffer(
            GL.GL_DRAW_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, cb
        )
        GL.glFramebufferRenderbuffer(
            GL.GL_DRAW_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, db
        )
        self._main_fb_ms, self._main_cb_ms, self._main_db_ms = fb, cb, db
        # the picture is resolved (or, without MSAA, copied) into a second buffer, upside down
        self._main_cb = GL.glGenRenderbuffers(1)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._main_cb)
        GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA8, w, h)
        self._main_fb = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._main_fb)
        GL.glFramebufferRenderbuffer(
            GL.GL_DRAW_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, self._main_cb
        )
        self._main_db = None
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, fb)  # pyrender draws into the first
        self._main_fb_dims = (w, h)

    def read(
        self: _pr_renderer.Renderer, scene: pyrender.Scene, flags: int
    ) -> tuple[np.ndarray | None, None]:
        if getattr(self, "_facelab_defer_read", False):
            GL.glFlush()  # the rasteriser starts now; read_now() collects the picture
            return None, None
        return read_now(self), None

    def scissor(self: _pr_renderer.Renderer, box: _Box | None) -> None:
        """Limit the next resolve to ``box`` joined with the last *resolved* box (whatever
        that frame left is replaced now); None: the whole frame. Invariant: outside the last
        resolved box the resolved picture is the background - kept when a frame is drawn and
        never read back (an error mid-clip): the box is recorded by the resolve, not here.
        Clearing and drawing cover the whole framebuffer (see the module docstring)."""
        w, h = self.viewport_width, self.viewport_height
        last = getattr(self, "_facelab_last_box", None)
        full = (0, 0, w, h)
        self._facelab_box = full if box is None or last is None else _union(box, last)
        self._facelab_drawn_box = box
        GL.glDisable(GL.GL_SCISSOR_TEST)

    def read_now(self: _pr_renderer.Renderer) -> np.ndarray:
        """The picture as (h, w, 3) uint8 RGB, top row first: the resolve blit turns it
        upside down (GL's rows run bottom up), so it is read back as it is."""
        w, h = self._main_fb_dims
        x, y, bw, bh = getattr(self, "_facelab_box", None) or (0, 0, w, h)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb_ms)
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._main_fb)
        flipped = (x, h - y, x + bw, h - y - bh)  # the destination's rows upside down
        GL.glBlitFramebuffer(
            x, y, x + bw, y + bh, *flipped, GL.GL_COLOR_BUFFER_BIT, GL.GL_NEAREST
        )
        self._facelab_last_box = getattr(self, "_facelab_drawn_box", None)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb)
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        # outputType None: the array itself (writeable), not bytes on older numpy
        buf = GL.glReadPixels(0, 0, w, h, GL.GL_RGB, GL.GL_UNSIGNED_BYTE, outputType=None)
        return np.asarray(buf, dtype=np.uint8).reshape(h, w, 3)

    def delete_fb(self: _pr_renderer.Renderer) -> None:
        for fb in {self._main_fb, self._main_fb_ms} - {None}:
            GL.glDeleteFramebuffers(1, [fb])
        for rb in {self._main_cb, self._main_db, self._main_cb_ms, self._main_db_ms} - {None}:
            GL.glDeleteRenderbuffers(1, [rb])
        self._main_fb = self._main_cb = self._main_db = None
        self._main_fb_ms = self._main_cb_ms = self._main_db_ms = None
        self._main_fb_dims = (None, None)
        self._facelab_last_box = None  # a new framebuffer is drawn whole first

    import types

    renderer._configure_main_framebuffer = types.MethodType(configure, renderer)
    renderer._read_main_framebuffer = types.MethodType(read, renderer)
    renderer._facelab_read = types.MethodType(read_now, renderer)
    renderer._delete_main_framebuffer = types.MethodType(delete_fb, renderer)
    renderer._facelab_scissor = types.MethodType(scissor, renderer)
