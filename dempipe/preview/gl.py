"""Offscreen OpenGL drawing of preview frames with moderngl (EGL, no display needed).

On a machine without a GPU, Mesa's llvmpipe rasterizes on the CPU through EGL: the
system needs libEGL, libGL and Mesa's drivers (:data:`SYSTEM_HINT`, docs/preview.md). With a
GPU and its driver's libEGL, the same code runs on the GPU.

A frame is drawn in passes: the bodies into a shadow map from a sun above; the bodies,
flat shaded (normals from screen-space derivatives, so any winding is fine) with sky and
ground ambient light and the sun's shadows; static geometry (colliders), opaque where it
does not hide the bodies and faded where it stands between the camera and their box (the
lid and front walls of a box); or, when the stage has no static geometry, a ground grid.
"""

from __future__ import annotations

import math
import sys

import numpy as np

from dempipe.preview.camera import Camera, to_stage
from dempipe.preview.reader import Batch, Geometry, PreviewError

INSTALL_HINT = ("pip install 'dempipe[preview]'")

#: How to get the system libraries EGL rendering needs (docs/preview.md).
SYSTEM_HINT = ("needs libEGL, libGL and Mesa's drivers (Debian/Ubuntu: apt-get install libegl1 "
               "libegl-mesa0 libgl1 libgl1-mesa-dri; RHEL/Rocky: dnf install mesa-libEGL "
               "mesa-libGL mesa-dri-drivers)")

_VERTEX = """
#version 330
in vec3 in_pos;
in vec4 in_m0; in vec4 in_m1; in vec4 in_m2; in vec4 in_m3;
in vec3 in_color;
uniform mat4 u_vp;
uniform mat4 u_light_vp;
out vec3 v_world;
out vec3 v_color;
out vec4 v_light;
void main() {
    // pxr's row-vector convention: p_world = [p, 1] @ M
    vec4 w = in_pos.x * in_m0 + in_pos.y * in_m1 + in_pos.z * in_m2 + in_m3;
    v_world = w.xyz / w.w;
    v_color = in_color;
    v_light = u_light_vp * vec4(v_world, 1.0);
    gl_Position = u_vp * vec4(v_world, 1.0);
}
"""

_FRAGMENT = """
#version 330
in vec3 v_world;
in vec3 v_color;
in vec4 v_light;
uniform vec3 u_eye;
uniform vec3 u_sun;         // towards the sun
uniform vec3 u_up;
uniform sampler2DShadow u_shadow;
uniform float u_shadow_bias;
uniform int u_mode;         // 0 body, 1 static opaque, 2 static faded, 3 ground grid
uniform vec3 u_box_lo;      // the bodies' box, for the cut-away of static geometry
uniform vec3 u_box_hi;
uniform vec3 u_grid_x;
uniform vec3 u_grid_y;
uniform float u_grid_step;
out vec4 f_color;

float lit(vec3 n) {
    vec3 p = v_light.xyz / v_light.w * 0.5 + 0.5;
    if (p.x <= 0.0 || p.x >= 1.0 || p.y <= 0.0 || p.y >= 1.0 || p.z >= 1.0) return 1.0;
    float bias = u_shadow_bias * (1.0 + 2.0 * (1.0 - abs(dot(n, u_sun))));
    float s = 0.0;
    vec2 texel = 1.0 / vec2(textureSize(u_shadow, 0));
    for (int i = -1; i <= 1; i++)
        for (int j = -1; j <= 1; j++)
            s += texture(u_shadow, vec3(p.xy + vec2(i, j) * texel, p.z - bias));
    return s / 9.0;
}

bool before_bodies() {
    // Is this fragment between the eye and the bodies' box along its ray?
    vec3 d = v_world - u_eye;
    float dist = length(d);
    d /= dist;
    vec3 inv = 1.0 / d;
    vec3 t0 = (u_box_lo - u_eye) * inv;
    vec3 t1 = (u_box_hi - u_eye) * inv;
    vec3 tmin = min(t0, t1);
    vec3 tmax = max(t0, t1);
    float enter = max(max(tmin.x, tmin.y), max(tmin.z, 0.0));
    float leave = min(min(tmax.x, tmax.y), tmax.z);
    return enter <= leave && dist < enter;
}

void main() {
    if (u_mode == 1 && before_bodies()) discard;
    if (u_mode == 2 && !before_bodies()) discard;
    vec3 n = normalize(cross(dFdx(v_world), dFdy(v_world)));
    if (dot(n, u_eye - v_world) < 0.0) n = -n;
    vec3 base = v_color;
    if (u_mode == 3) {
        vec2 g = vec2(dot(v_world, u_grid_x), dot(v_world, u_grid_y)) / u_grid_step;
        vec2 w = fwidth(g);
        vec2 a = abs(fract(g - 0.5) - 0.5) / max(w, 1e-6);
        float line = 1.0 - min(min(a.x, a.y), 1.0);
        vec2 g10 = g / 10.0;
        vec2 a10 = abs(fract(g10 - 0.5) - 0.5) / max(fwidth(g10), 1e-6);
        float major = 1.0 - min(min(a10.x, a10.y), 1.0);
        float fade = clamp(1.0 - 0.5 * (w.x + w.y), 0.0, 1.0);
        base = mix(base, vec3(0.22), max(0.45 * line * fade, 0.8 * major));
    }
    float sun = max(dot(n, u_sun), 0.0) * lit(n);
    float hemi = 0.5 + 0.5 * dot(n, u_up);
    vec3 ambient = mix(vec3(0.20, 0.19, 0.18), vec3(0.42, 0.45, 0.52), hemi);
    vec3 c = base * (ambient + vec3(1.0, 0.97, 0.92) * 0.85 * sun);
    c = pow(clamp(c, 0.0, 1.0), vec3(1.0 / 2.2));     // USD colours are linear
    f_color = vec4(c, u_mode == 2 ? 0.18 : 1.0);
}
"""

_DEPTH_FRAGMENT = """
#version 330
void main() {}
"""

BACKGROUND = (0.80, 0.82, 0.85)


def _moderngl():
    try:
        import moderngl
    except ImportError:
        raise PreviewError(f"dempipe preview needs the preview extra: {INSTALL_HINT}") from None
    return moderngl


def create_context():
    """A standalone OpenGL 3.3 context: EGL on Linux (no display), the default elsewhere."""
    moderngl = _moderngl()
    errors = []
    backends = ["egl", None] if sys.platform.startswith("linux") else [None]
    for backend in backends:
        try:
            kw = {"backend": backend} if backend else {}
            return moderngl.create_standalone_context(require=330, **kw)
        except Exception as exc:   # missing libEGL, no usable driver, no display
            errors.append(f"{backend or 'default'}: {str(exc).strip().splitlines()[0]}")
    raise PreviewError("cannot create an offscreen OpenGL context (" + "; ".join(errors)
                       + f"); dempipe preview {SYSTEM_HINT}")


class Renderer:
    """Draws batches (reader.Batch) with a camera into an RGB picture (H, W, 3) uint8."""

    def __init__(self, width: int, height: int, *, samples: int = 4, shadow_size: int = 2048,
                 ctx=None):
        self.ctx = ctx or create_context()
        ctx = self.ctx
        self.width, self.height = int(width), int(height)
        self.program = ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
        self.depth_program = ctx.program(vertex_shader=_VERTEX, fragment_shader=_DEPTH_FRAGMENT)
        samples = min(samples, ctx.max_samples)
        size = (self.width, self.height)
        self.msaa = ctx.framebuffer(
            color_attachments=[ctx.renderbuffer(size, 4, samples=samples)],
            depth_attachment=ctx.depth_renderbuffer(size, samples=samples))
        self.resolved = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size, 4)])
        self.shadow_tex = ctx.depth_texture((shadow_size, shadow_size))
        self.shadow_tex.compare_func = "<="
        self.shadow_tex.repeat_x = self.shadow_tex.repeat_y = False
        self.shadow_fbo = ctx.framebuffer(depth_attachment=self.shadow_tex)
        self._buffers: dict[str, tuple] = {}
        self._quad = None

    def release(self):
        self.ctx.release()

    # ------------------------------------------------------------------ buffers

    def _geometry_buffers(self, geom):
        entry = self._buffers.get(geom.key)
        if entry is None or entry[2] is not geom:
            vbo = self.ctx.buffer(np.ascontiguousarray(geom.points, dtype="f4").tobytes())
            ibo = self.ctx.buffer(np.ascontiguousarray(geom.triangles, dtype="i4").tobytes())
            entry = (vbo, ibo, geom)
            self._buffers[geom.key] = entry
        return entry

    def _vao(self, program, vbo, ibo, inst):
        return self.ctx.vertex_array(
            program, [(vbo, "3f", "in_pos"),
                      (inst, "4f 4f 4f 4f 3f/i", "in_m0", "in_m1", "in_m2", "in_m3", "in_color")],
            index_buffer=ibo, index_element_size=4, skip_errors=True)

    def _draw(self, program, batches, mode=None):
        for b in batches:
            vbo, ibo, _ = self._geometry_buffers(b.geometry)
            data = np.concatenate([b.matrices.reshape(-1, 16), b.colors], axis=1)
            inst = self.ctx.buffer(np.ascontiguousarray(data, dtype="f4").tobytes())
            vao = self._vao(program, vbo, ibo, inst)
            if mode is not None:
                program["u_mode"].value = mode
            vao.render(instances=len(b.matrices))
            vao.release()
            inst.release()

    # ------------------------------------------------------------------ drawing

    def render(self, batches, camera: Camera, *, up_axis: str, bodies_box, light_box,
               ground=None) -> np.ndarray:
        """One picture. ``bodies_box``: (lo, hi) of this frame's bodies (cut-away);
        ``light_box``: what the shadow map covers; ``ground``: a grid to draw under the
        bodies (:func:`ground_grid`), or None."""
        ctx = self.ctx
        up = to_stage((0, 0, 1), up_axis)
        sun = to_stage((0.35, -0.25, 1.0), up_axis)
        sun /= np.linalg.norm(sun)
        bodies = [b for b in batches if b.body]
        statics = [b for b in batches if not b.body]
        light_vp, bias = _light_matrix(sun, up_axis, *light_box)

        prog = self.program
        prog["u_light_vp"].write(light_vp.T.astype("f4").tobytes())
        # 1: the bodies' depth seen from the sun
        self.shadow_fbo.use()
        self.shadow_fbo.clear(depth=1.0)
        ctx.enable(ctx.DEPTH_TEST)
        ctx.disable(ctx.BLEND)
        self.depth_program["u_vp"].write(light_vp.T.astype("f4").tobytes())
        self._draw(self.depth_program, bodies)

        # 2: the picture
        self.msaa.use()
        self.msaa.clear(*BACKGROUND, 1.0, depth=1.0)
        prog["u_vp"].write(camera.view_projection().T.astype("f4").tobytes())
        prog["u_eye"].value = tuple(map(float, camera.eye))
        prog["u_sun"].value = tuple(map(float, sun))
        prog["u_up"].value = tuple(map(float, up))
        prog["u_shadow_bias"].value = bias
        self.shadow_tex.use(location=0)
        prog["u_shadow"].value = 0
        lo, hi = bodies_box
        prog["u_box_lo"].value = tuple(map(float, lo))
        prog["u_box_hi"].value = tuple(map(float, hi))
        self._draw(prog, bodies, mode=0)
        self._draw(prog, statics, mode=1)
        if ground is not None:
            self._draw_ground(prog, up_axis, *ground)
        if statics:
            ctx.enable(ctx.BLEND)
            ctx.blend_func = ctx.SRC_ALPHA, ctx.ONE_MINUS_SRC_ALPHA
            ctx.depth_mask = False
            self._draw(prog, statics, mode=2)
            ctx.depth_mask = True
            ctx.disable(ctx.BLEND)
        ctx.copy_framebuffer(self.resolved, self.msaa)
        raw = self.resolved.read(components=3, alignment=1)
        img = np.frombuffer(raw, dtype=np.uint8).reshape(self.height, self.width, 3)
        return np.ascontiguousarray(img[::-1])

    def _draw_ground(self, prog, up_axis, height, step, half, centre):
        gx = to_stage((1, 0, 0), up_axis)
        gy = to_stage((0, 1, 0), up_axis)
        up = to_stage((0, 0, 1), up_axis)
        if self._quad is None:
            pts = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
            self._quad = Geometry("__ground__", pts, np.array([[0, 1, 2], [0, 2, 3]], np.int32))
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = gx * half, gy * half, up
        centre = np.asarray(centre, np.float64)
        m[3, :3] = centre - up * (centre @ up) + up * height
        prog["u_grid_x"].value = tuple(map(float, gx))
        prog["u_grid_y"].value = tuple(map(float, gy))
        prog["u_grid_step"].value = float(step)
        self._draw(prog, [Batch(self._quad, m[None], np.array([[0.62, 0.62, 0.60]], np.float32),
                                False)], mode=3)


def _light_matrix(sun, up_axis, lo, hi):
    """Orthographic view-projection of the sun covering the sphere about [lo, hi]."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-6) * 1.05
    eye = centre + sun * 2 * radius
    f = -sun
    helper = to_stage((0, 1, 0), up_axis)
    r = np.cross(f, helper)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = r, u, -f
    view[:3, 3] = -view[:3, :3] @ eye
    n, far = 0.0, 4 * radius
    proj = np.diag([1 / radius, 1 / radius, -2 / (far - n), 1.0])
    proj[2, 3] = -(far + n) / (far - n)
    # one and a half shadow-map texels of depth, in the [0, 1] depth range
    bias = 1.5 * (2 * radius / 2048) / (far - n)
    return proj @ view, float(bias)


def ground_grid(lo, hi, up_axis):
    """(height, line step, half size, centre) of a grid under a box: 1-2-5 steps, ~10 lines
    across the box."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    axis = 1 if up_axis == "Y" else 2
    span = max(float(np.max(np.delete(hi - lo, axis))), float(hi[axis] - lo[axis]), 1e-6)
    raw = span / 10
    mag = 10 ** math.floor(math.log10(raw))
    step = min((s * mag for s in (1, 2, 5, 10) if s * mag >= raw), default=10 * mag)
    return float(lo[axis]), float(step), float(span * 4), (lo + hi) / 2
