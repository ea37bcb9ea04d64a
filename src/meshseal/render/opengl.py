"""An independent real-OpenGL renderer (moderngl, headless EGL) following docs/conventions.md.

Used as ground truth in tests, as the speed reference in the render benchmark, and as the
user-facing "OpenGL" backend. It is not differentiable.

- Camera: clip = P @ V @ [x, y, z, 1] with the matrices of `Cameras`; triangles with any vertex at
  clip.w <= near are dropped (geometry shader), no back-face culling.
- Pixels: image row 0 is the top; GL's pixel centres (j + 0.5, i + 0.5) match the conventions.
- Texture: bilinear (GL_LINEAR, no mipmaps), REPEAT, uv (0, 0) = bottom-left of the image
  (the image is uploaded bottom row first, so v = 1 is image row 0). Float32 texels.
- Shading: per-fragment Phong exactly as in docs/conventions.md, clamped to [0, 1].
- Output: float32 RGBA render target, 24-bit depth buffer, no MSAA; alpha = coverage (0 or 1).

Several images are rendered as vertical tiles of one framebuffer (one viewport per image) and
read back with a single glReadPixels.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from .cameras import Cameras
from .lighting import ATTENUATION, K_AMBIENT, K_DIFFUSE, K_SPECULAR, PointLights

MAX_LIGHTS = 8
DEFAULT_MATERIAL = dict(ambient=(0.25, 0.25, 0.25), diffuse=(1.0, 1.0, 1.0), specular=(0.0, 0.0, 0.0),
                        shininess=32.0)
# Upper bound of framebuffer pixels per chunk of tiles (float32 RGBA + depth: 20 bytes a pixel).
_MAX_TILE_PIXELS = 4 * 1024 * 1024

_VERTEX_SHADER = """
#version 330
uniform mat4 mvp;
in vec3 in_pos;
in vec3 in_normal;
in vec2 in_uv;
out vec3 g_pos;
out vec3 g_normal;
out vec2 g_uv;
void main() {
    g_pos = in_pos;
    g_normal = in_normal;
    g_uv = in_uv;
    gl_Position = mvp * vec4(in_pos, 1.0);
}
"""

# Drops triangles with any vertex at clip.w <= near (conventions: no near-plane clipping).
_GEOMETRY_SHADER = """
#version 330
layout(triangles) in;
layout(triangle_strip, max_vertices = 3) out;
uniform float near;
in vec3 g_pos[];
in vec3 g_normal[];
in vec2 g_uv[];
out vec3 f_pos;
out vec3 f_normal;
out vec2 f_uv;
void main() {
    if (gl_in[0].gl_Position.w <= near || gl_in[1].gl_Position.w <= near || gl_in[2].gl_Position.w <= near)
        return;
    for (int i = 0; i < 3; ++i) {
        gl_Position = gl_in[i].gl_Position;
        f_pos = g_pos[i];
        f_normal = g_normal[i];
        f_uv = g_uv[i];
        EmitVertex();
    }
    EndPrimitive();
}
"""

_FRAGMENT_SHADER = """
#version 330
#define MAX_LIGHTS %d
uniform sampler2DArray tex;  // planar: layers 3 k, 3 k + 1, 3 k + 2 are R, G, B of texture k
uniform float layer;         // 3 k
uniform vec3 eye;
uniform int n_lights;
uniform vec3 light_pos[MAX_LIGHTS];
uniform vec3 light_int[MAX_LIGHTS];
uniform vec3 mat_ambient;
uniform vec3 mat_diffuse;
uniform vec3 mat_specular;
uniform float shininess;
uniform float ka;
uniform float kd;
uniform float kr;
uniform vec3 att_coef;
in vec3 f_pos;
in vec3 f_normal;
in vec2 f_uv;
out vec4 frag_color;
void main() {
    vec3 n = normalize(f_normal);
    vec3 to_eye = eye - f_pos;
    if (dot(n, to_eye) < 0.0) n = -n;
    vec3 v = normalize(to_eye);
    // Layers are uploaded top row first, so t = 1 - v puts uv (0, 0) at the image's bottom-left.
    vec2 st = vec2(f_uv.x, 1.0 - f_uv.y);
    vec3 albedo = vec3(texture(tex, vec3(st, layer)).r, texture(tex, vec3(st, layer + 1.0)).r,
                       texture(tex, vec3(st, layer + 2.0)).r) * mat_diffuse;
    vec3 color = ka * mat_ambient * albedo;
    for (int k = 0; k < n_lights; ++k) {
        vec3 to_light = light_pos[k] - f_pos;
        float d = length(to_light);
        vec3 l = to_light / d;
        float att = att_coef.x + att_coef.y * d + att_coef.z * d * d;
        float nl = dot(n, l);
        vec3 r = 2.0 * nl * n - l;
        float rv = max(dot(r, v), 0.0);
        float s = rv > 0.0 ? pow(rv, shininess) : (shininess == 0.0 ? 1.0 : 0.0);
        color += light_int[k] / att * (kd * max(nl, 0.0) * albedo + kr * mat_specular * s);
    }
    frag_color = vec4(clamp(color, 0.0, 1.0), 1.0);
}
""" % MAX_LIGHTS


def _np(x, dtype=np.float32) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.ascontiguousarray(np.asarray(x), dtype=dtype)


def _rgb(value) -> tuple[float, float, float]:
    a = _np(value).reshape(-1)
    if a.size == 1:
        a = np.repeat(a, 3)
    return tuple(float(c) for c in a[:3])


def _planar(images) -> np.ndarray:
    """(N, 3, H, W) or (H, W, C) float images (row 0 = top) -> (3 N, H, W) float32 planar layers."""
    if isinstance(images, torch.Tensor):
        images = images.detach().cpu()
        if images.dim() == 2:
            images = images.unsqueeze(-1)
        if images.dim() == 3:  # (H, W, C) -> (1, 3, H, W)
            images = images[..., :3].expand(-1, -1, 3) if images.shape[-1] == 1 else images[..., :3]
            images = images.permute(2, 0, 1).unsqueeze(0)
        images = images.to(torch.float32).contiguous().numpy()
    images = np.asarray(images, np.float32)
    if images.ndim == 3:
        images = np.repeat(images, 3, -1) if images.shape[-1] == 1 else images[..., :3]
        images = images.transpose(2, 0, 1)[None]
    n, c, h, w = images.shape
    return np.ascontiguousarray(images, np.float32).reshape(n * c, h, w)


class OpenGLRenderer:
    """Headless OpenGL (moderngl + EGL) Phong renderer; see the module docstring for conventions.

    The context is created on first use and reused. `ka`, `kd`, `kr` default to the seed's
    constants in `lighting.py`.
    """

    def __init__(self, backend: str = "egl", ka: float = K_AMBIENT, kd: float = K_DIFFUSE,
                 kr: float = K_SPECULAR):
        self.backend = backend
        self.ka, self.kd, self.kr = float(ka), float(kd), float(kr)
        self._context = None
        self._program = None
        self._white = None
        self._fbo_cache: dict = {}
        self._batch_cache: dict = {}

    # ------------------------------------------------------------------ context
    @property
    def ctx(self):
        if self._context is None:
            try:
                import moderngl
                kwargs = {"backend": self.backend} if self.backend else {}
                self._context = moderngl.create_standalone_context(require=330, **kwargs)
            except Exception as error:  # ImportError, missing libEGL, no device, ...
                message = " ".join(str(error).split()) or type(error).__name__
                raise RuntimeError(f"OpenGL renderer unavailable: cannot create a headless "
                                   f"{self.backend or 'default'} OpenGL context ({message})") from None
            self._program = self._context.program(vertex_shader=_VERTEX_SHADER,
                                                  geometry_shader=_GEOMETRY_SHADER,
                                                  fragment_shader=_FRAGMENT_SHADER)
            self._program["tex"].value = 0
            self._white = self._make_texture(np.ones((1, 1, 3), np.float32))
        return self._context

    @property
    def info(self) -> dict:
        return dict(self.ctx.info)

    def release(self) -> None:
        """Free all GL objects and the context (a later render creates a new one)."""
        if self._context is not None:
            self._context.release()
        self._context, self._program, self._white = None, None, None
        self._fbo_cache.clear()
        self._batch_cache.clear()

    def _make_texture(self, image):
        """A planar float32 texture array (3 layers) from one (H, W, C) image."""
        data = _planar(image)
        n, h, w = data.shape
        texture = self.ctx.texture_array((w, h, n), 1, data, dtype="f4", alignment=4)
        self._set_sampling(texture)
        return texture

    @staticmethod
    def _set_sampling(texture) -> None:
        import moderngl
        texture.filter = (moderngl.LINEAR, moderngl.LINEAR)
        texture.repeat_x = True
        texture.repeat_y = True

    def _framebuffer(self, width: int, height: int, tiles: int):
        key = (width, height, tiles)
        fbo = self._fbo_cache.get(key)
        if fbo is None:
            if len(self._fbo_cache) >= 4:
                for old in self._fbo_cache.values():
                    for attachment in (*old.color_attachments, old.depth_attachment):
                        attachment.release()
                    old.release()
                self._fbo_cache.clear()
            color = self.ctx.texture((width, height * tiles), 4, dtype="f4")
            depth = self.ctx.depth_renderbuffer((width, height * tiles))
            fbo = self.ctx.framebuffer(color_attachments=[color], depth_attachment=depth)
            self._fbo_cache[key] = fbo
        return fbo

    def _tiles_per_chunk(self, width: int, height: int) -> int:
        max_size = min(self.ctx.info["GL_MAX_TEXTURE_SIZE"], self.ctx.info["GL_MAX_RENDERBUFFER_SIZE"],
                       self.ctx.info["GL_MAX_VIEWPORT_DIMS"][1])
        if width > max_size or height > max_size:
            raise ValueError(f"OpenGL renderer: image size {width}x{height} exceeds the GL limit {max_size}")
        return max(1, min(max_size // height, _MAX_TILE_PIXELS // (width * height)))

    # ------------------------------------------------------------------ per-image uniforms
    @staticmethod
    def _view_uniforms(cameras: Cameras, lights: PointLights, width: int, height: int):
        aspect = width / height
        view = cameras.view_matrix().detach().cpu().to(torch.float32)
        proj = cameras.projection_matrix(aspect).detach().cpu().to(torch.float32)
        # Negating clip y renders row 0 (the top) into GL's first (bottom) framebuffer row. The pixel
        # centres are unchanged: GL row k samples ndc_y = 1 - 2 (k + 0.5) / H = image row k. Only the
        # winding flips (irrelevant: no culling) and the fill-rule tie-break on exact edges.
        flip = torch.diag(torch.tensor([1.0, -1.0, 1.0, 1.0]))
        mvp = (flip @ proj).unsqueeze(0) @ view
        mvp = mvp.numpy()  # (B, 4, 4) row-major
        eye = _np(cameras.eye)
        light_pos = _np(lights.position)
        light_int = _np(lights.intensity)
        if light_pos.ndim == 2:  # (B, 3): one light per image
            light_pos, light_int = light_pos[:, None], light_int[:, None]
        if light_int.shape != light_pos.shape:
            light_int = np.ascontiguousarray(np.broadcast_to(light_int, light_pos.shape), np.float32)
        if light_pos.shape[0] != mvp.shape[0]:
            raise ValueError(f"OpenGL renderer: {mvp.shape[0]} cameras but {light_pos.shape[0]} light sets")
        if light_pos.shape[1] > MAX_LIGHTS:
            raise ValueError(f"OpenGL renderer supports at most {MAX_LIGHTS} lights, got {light_pos.shape[1]}")
        return mvp, eye, light_pos, light_int

    def _set_view(self, b: int, mvp, eye, light_pos, light_int, near: float) -> None:
        program = self._program
        # numpy is row-major, GLSL mat4 uniforms are column-major: upload the transpose's bytes.
        program["mvp"].write(np.ascontiguousarray(mvp[b].T, dtype=np.float32).tobytes())
        program["eye"].value = tuple(float(c) for c in eye[b])
        program["near"].value = float(near)
        n = light_pos.shape[1]
        padded_pos = np.zeros((MAX_LIGHTS, 3), np.float32)
        padded_int = np.zeros((MAX_LIGHTS, 3), np.float32)
        padded_pos[:n], padded_int[:n] = light_pos[b], light_int[b]
        program["light_pos"].write(padded_pos.tobytes())
        program["light_int"].write(padded_int.tobytes())
        program["n_lights"].value = n

    def _set_constants(self) -> None:
        program = self._program
        program["ka"].value = self.ka
        program["kd"].value = self.kd
        program["kr"].value = self.kr
        program["att_coef"].value = tuple(float(c) for c in ATTENUATION)

    def _set_material(self, ambient, diffuse, specular, shininess) -> None:
        program = self._program
        program["mat_ambient"].value = _rgb(ambient)
        program["mat_diffuse"].value = _rgb(diffuse)
        program["mat_specular"].value = _rgb(specular)
        program["shininess"].value = float(shininess)

    @staticmethod
    def _readback(fbo, width: int, height: int, tiles: int) -> torch.Tensor:
        # The projection is flipped in y (see _view_uniforms), so GL's first row is image row 0
        # and tile b occupies GL rows [b H, (b + 1) H): the framebuffer is already (B, H, W, 4).
        out = torch.empty(tiles, height, width, 4, dtype=torch.float32)
        fbo.read_into(out.numpy(), viewport=(0, 0, width, height * tiles), components=4, dtype="f4")
        return out

    def _begin(self, fbo, background) -> None:
        import moderngl
        fbo.use()
        fbo.viewport = (0, 0, *fbo.size)
        bg = _rgb(background)
        fbo.clear(bg[0], bg[1], bg[2], 0.0, depth=1.0)
        self.ctx.enable_only(moderngl.DEPTH_TEST)
        self.ctx.depth_func = "<"

    # ------------------------------------------------------------------ public API
    def render(self, mesh, cameras: Cameras, lights: PointLights, width: int, height: int,
               background: Sequence[float] = (0.0, 0.0, 0.0)) -> torch.Tensor:
        """Render one (multi-material) mesh from B cameras -> float32 (B, H, W, 4) in [0, 1].

        Row 0 is the top; alpha is coverage. `lights` has one light set per camera.
        """
        import moderngl
        ctx = self.ctx
        width, height = int(width), int(height)
        mvp, eye, light_pos, light_int = self._view_uniforms(cameras, lights, width, height)
        batch = mvp.shape[0]

        if getattr(mesh, "normals", None) is None:
            raise ValueError("OpenGL renderer: the mesh has no vertex normals")
        positions = _np(mesh.positions)
        normals = _np(mesh.normals)
        n_vertices = positions.shape[0]
        has_uv = getattr(mesh, "uvs", None) is not None
        uvs = _np(mesh.uvs) if has_uv else np.zeros((n_vertices, 2), np.float32)
        faces = _np(mesh.faces, np.int64).reshape(-1, 3)
        face_material = getattr(mesh, "face_material", None)
        face_material = (np.zeros(len(faces), np.int64) if face_material is None
                         else _np(face_material, np.int64).reshape(-1))
        materials = list(getattr(mesh, "materials", None) or [])

        owned = []
        vbo_pos = ctx.buffer(positions.tobytes())
        vbo_nrm = ctx.buffer(normals.tobytes())
        vbo_uv = ctx.buffer(uvs.tobytes())
        owned += [vbo_pos, vbo_nrm, vbo_uv]
        draws = []  # (vao, texture, material)
        textures: dict[int, object] = {}
        for index in np.unique(face_material):
            subset = faces[face_material == index].astype(np.uint32)
            if len(subset) == 0:
                continue
            material = materials[index] if 0 <= index < len(materials) else None
            image = getattr(material, "texture", None) if material is not None else None
            if image is None or not has_uv:
                texture = self._white
            else:
                key = id(image)
                if key not in textures:
                    textures[key] = self._make_texture(image)
                    owned.append(textures[key])
                texture = textures[key]
            ibo = ctx.buffer(subset.tobytes())
            vao = ctx.vertex_array(self._program, [(vbo_pos, "3f", "in_pos"), (vbo_nrm, "3f", "in_normal"),
                                                   (vbo_uv, "2f", "in_uv")],
                                   index_buffer=ibo, index_element_size=4)
            owned += [ibo, vao]
            draws.append((vao, texture, material))

        def draw(b: int) -> None:
            for vao, texture, material in draws:
                if material is None:
                    self._set_material(**DEFAULT_MATERIAL)
                else:
                    self._set_material(material.ambient, material.diffuse, material.specular, material.shininess)
                texture.use(0)
                vao.render(moderngl.TRIANGLES)

        try:
            self._set_constants()
            self._program["layer"].value = 0.0
            return self._render_tiles(batch, width, height, background, mvp, eye, light_pos, light_int,
                                      cameras.near, draw)
        finally:
            for obj in owned:
                obj.release()

    def _render_tiles(self, batch, width, height, background, mvp, eye, light_pos, light_int, near, draw):
        """Draw each image into its own vertical tile of a shared framebuffer (`draw(b)` issues the draw
        calls of image b), reading back one chunk of tiles at a time -> (B, H, W, 4)."""
        per_chunk = self._tiles_per_chunk(width, height)
        results = []
        for start in range(0, batch, per_chunk):
            tiles = min(per_chunk, batch - start)
            fbo = self._framebuffer(width, height, tiles)
            self._begin(fbo, background)
            for t in range(tiles):
                b = start + t
                fbo.viewport = (0, t * height, width, height)
                self._set_view(b, mvp, eye, light_pos, light_int, near)
                draw(b)
            results.append(self._readback(fbo, width, height, tiles))
        return torch.cat(results, 0) if len(results) > 1 else results[0]

    def render_batch(self, positions: torch.Tensor, normals: torch.Tensor, uvs: torch.Tensor,
                     faces: torch.Tensor, textures: torch.Tensor, cameras: Cameras, lights: PointLights,
                     width: int, height: int, background: Sequence[float] = (0.0, 0.0, 0.0)) -> torch.Tensor:
        """Render B same-topology meshes, each with its own texture and the default material.

        positions, normals (B, V, 3) (or (V, 3), shared); uvs (B, V, 2) or (V, 2); faces (F, 3) or
        (B, F, 3); textures (B, 3, Ht, Wt) in [0, 1]; B cameras and light sets -> (B, H, W, 4).
        GL buffers are kept between calls of the same sizes and refilled with one write each.
        """
        import moderngl
        ctx = self.ctx
        width, height = int(width), int(height)
        mvp, eye, light_pos, light_int = self._view_uniforms(cameras, lights, width, height)
        batch = mvp.shape[0]

        def per_mesh(x, last):
            x = x.detach()
            if x.dim() == 2:
                x = x.unsqueeze(0).expand(batch, -1, -1)
            if x.shape[0] != batch or x.shape[-1] != last:
                raise ValueError(f"OpenGL render_batch: expected ({batch}, N, {last}), got {tuple(x.shape)}")
            return x

        positions, normals = per_mesh(positions, 3), per_mesh(normals, 3)
        n_vertices = positions.shape[1]
        uvs = (torch.zeros(batch, n_vertices, 2) if uvs is None else per_mesh(uvs, 2))
        faces = faces.detach().cpu().to(torch.int64)
        if faces.dim() == 2:
            faces = faces.unsqueeze(0).expand(batch, -1, -1)
        n_faces = faces.shape[1]
        offsets = (torch.arange(batch, dtype=torch.int64) * n_vertices).view(batch, 1, 1)
        indices = (faces + offsets).to(torch.int32)
        if textures.dim() == 3:
            textures = textures.unsqueeze(0).expand(batch, -1, -1, -1)
        if textures.shape[0] != batch or textures.shape[1] != 3:
            raise ValueError(f"OpenGL render_batch: textures must be ({batch}, 3, H, W), got {tuple(textures.shape)}")
        # (B, 3, Ht, Wt) is uploaded as it is: 3 B single-channel layers (no reordering on the CPU).
        texels = textures.detach().cpu().to(torch.float32).contiguous()
        tex_h, tex_w = texels.shape[2], texels.shape[3]

        key = (batch, n_vertices, n_faces, tex_w, tex_h)
        cache = self._batch_cache.get(key)
        if cache is None:
            if len(self._batch_cache) >= 4:
                for old in self._batch_cache.values():
                    for obj in old.values():
                        obj.release()
                self._batch_cache.clear()
            vbo_pos = ctx.buffer(reserve=batch * n_vertices * 12)
            vbo_nrm = ctx.buffer(reserve=batch * n_vertices * 12)
            vbo_uv = ctx.buffer(reserve=batch * n_vertices * 8)
            ibo = ctx.buffer(reserve=batch * n_faces * 12)
            texture = ctx.texture_array((tex_w, tex_h, 3 * batch), 1, dtype="f4", alignment=4)
            self._set_sampling(texture)
            vao = ctx.vertex_array(self._program, [(vbo_pos, "3f", "in_pos"), (vbo_nrm, "3f", "in_normal"),
                                                   (vbo_uv, "2f", "in_uv")],
                                   index_buffer=ibo, index_element_size=4)
            cache = dict(vbo_pos=vbo_pos, vbo_nrm=vbo_nrm, vbo_uv=vbo_uv, ibo=ibo, texture=texture, vao=vao)
            self._batch_cache[key] = cache

        def upload(buffer, tensor):
            buffer.write(tensor.cpu().to(torch.float32).contiguous().numpy())  # no copy if already so

        upload(cache["vbo_pos"], positions)
        upload(cache["vbo_nrm"], normals)
        upload(cache["vbo_uv"], uvs)
        cache["ibo"].write(indices.contiguous().numpy())
        cache["texture"].write(texels.numpy())
        cache["texture"].use(0)

        def draw(b: int) -> None:
            self._program["layer"].value = float(3 * b)
            cache["vao"].render(moderngl.TRIANGLES, vertices=n_faces * 3, first=b * n_faces * 3)

        self._set_constants()
        self._set_material(**DEFAULT_MATERIAL)
        return self._render_tiles(batch, width, height, background, mvp, eye, light_pos, light_int,
                                  cameras.near, draw)


__all__ = ["OpenGLRenderer", "MAX_LIGHTS"]
