"""Pictures of a bake without a DCC: stills, movies and contact sheets (`dempipe preview`).

    from dempipe import preview
    preview.render_frame("chess.usdc", "chess.png", frame=72)
    preview.render_movie("chess.usdc", "chess.mp4", progress=print)
    preview.contact_sheet(["a.usdc", "b.usdc"], "wedge.png", labels=["k=1", "k=2"])

Reads any USD stage (both dempipe layouts, overlays, files from other tools; reader.py),
draws it offscreen with OpenGL through moderngl and EGL (gl.py; on a machine without a GPU
Mesa's llvmpipe draws on the CPU), writes PNG and GIF with Pillow and MP4 (H.264) with
PyAV, whose wheel ships FFmpeg. These come with the optional extra ``dempipe[preview]``;
without it every function raises :class:`PreviewError` saying how to install it.
Every file is written to a temporary name beside the target and moved over it.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from dempipe.preview.camera import PRESETS, Camera, frame_box
from dempipe.preview.reader import PreviewError, StageReader, batch_bounds

__all__ = ["Preview", "PreviewError", "render_frame", "render_movie", "contact_sheet",
           "parse_size", "parse_frames", "CAMERAS", "require"]

CAMERAS = tuple(PRESETS)
STILL_EXTENSIONS = (".png",)
MOVIE_EXTENSIONS = (".mp4", ".gif")
DEFAULT_SIZE = (1280, 720)
#: Instanced triangles drawn at most; above it the bodies' shared meshes are coarsened
#: (reader.simplify). llvmpipe transforms vertices on one thread: 1,024 chess pieces at
#: full detail (2.8 M triangles) cost ~1 s of CPU a frame, at this budget a fraction.
TRIANGLE_BUDGET = 600_000
#: Multisampling: stills and contact sheets 4x, movies none (a frame of the chess bake
#: costs 2.7x the CPU with 4x; docs/preview.md "Speed").
STILL_SAMPLES, MOVIE_SAMPLES = 4, 0

_EXTRA = ("dempipe preview needs the preview extra (moderngl, av, pillow): "
          "pip install 'dempipe[preview]'")


def require(*modules: str) -> None:
    """Raise PreviewError with the install line unless every module imports."""
    import importlib

    for name in modules or ("moderngl", "PIL"):
        try:
            importlib.import_module(name)
        except ImportError:
            raise PreviewError(_EXTRA) from None


def parse_size(text: str) -> tuple[int, int]:
    """'WxH' → (W, H), each 16 to 8192 pixels."""
    try:
        w, h = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise PreviewError(f"--size: expected WIDTHxHEIGHT (e.g. 1280x720), got {text!r}") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise PreviewError(f"--size: {w}x{h} is outside 16x16 to 8192x8192")
    return w, h


def parse_frames(text: str | None, frames: list[int], name: str = "the bake") -> list[int]:
    """'A:B' (inclusive frame numbers, either end may be left out) → the frames in it."""
    if not text:
        return list(frames)
    try:
        a, b = str(text).split(":")
        start = int(a) if a.strip() else frames[0]
        end = int(b) if b.strip() else frames[-1]
    except ValueError:
        raise PreviewError(f"--frames: expected START:END (e.g. 0:48), got {text!r}") from None
    chosen = [f for f in frames if start <= f <= end]
    if start > end or start < frames[0] or end > frames[-1] or not chosen:
        raise PreviewError(f"--frames {start}:{end}: outside {name}'s frames "
                           f"{frames[0]}:{frames[-1]}")
    return chosen


class Preview:
    """One bake, opened for pictures: ``Preview(path).image(frame)`` → (H, W, 3) uint8.

    ``camera`` is a preset name (:data:`CAMERAS`); the preset frames the bodies' bounds at
    the bake's first and last frames, so every frame of a movie shares one camera. The
    camera used is ``self.camera`` (``self.camera.project(points)`` gives pixels).
    """

    def __init__(self, path, *, size=DEFAULT_SIZE, camera: str = "three-quarter",
                 samples: int = STILL_SAMPLES, renderer=None):
        require()
        if camera not in PRESETS:
            raise PreviewError(f"--camera: unknown camera {camera!r} (known: "
                               f"{', '.join(PRESETS)})")
        self.reader = StageReader(path)
        self.path = self.reader.path
        self.frames = self.reader.frames
        self.width, self.height = (int(v) for v in size)
        first = self.reader.batches(self.frames[0])
        self.triangles = self.reader.simplify_bodies(TRIANGLE_BUDGET, first)
        first = self.reader.batches(self.frames[0])
        last = first if len(self.frames) == 1 else self.reader.batches(self.frames[-1])
        boxes = [b for b in (batch_bounds(first), batch_bounds(last)) if b is not None]
        self.has_bodies = bool(boxes)
        if not boxes:       # a still stage: frame everything
            boxes = [batch_bounds(first, bodies_only=False)]
        lo = np.min([b[0] for b in boxes], axis=0)
        hi = np.max([b[1] for b in boxes], axis=0)
        self.bounds = (lo, hi)
        everything = batch_bounds(first, bodies_only=False)
        radius = float(np.linalg.norm(np.maximum(np.abs(everything[1] - (lo + hi) / 2),
                                                 np.abs(everything[0] - (lo + hi) / 2))))
        self.camera: Camera = frame_box(camera, lo, hi, self.reader.up_axis, self.width,
                                        self.height, scene_radius=radius)
        self.has_statics = any(not b.body for b in first)
        self.samples = int(samples)
        self._renderer = renderer
        self._own_renderer = renderer is None

    @property
    def renderer(self):
        if self._renderer is None:
            from dempipe.preview.gl import Renderer

            self._renderer = Renderer(self.width, self.height, samples=self.samples)
        return self._renderer

    def close(self):
        if self._own_renderer and self._renderer is not None:
            self._renderer.release()
            self._renderer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def image(self, frame: int | None = None) -> np.ndarray:
        """The picture of time code ``frame`` (default: the last frame)."""
        from dempipe.preview.gl import ground_grid

        frame = self.frames[-1] if frame is None else int(frame)
        self.reader.check_frame(frame)
        batches = self.reader.batches(frame)
        box = batch_bounds(batches) if self.has_bodies else None
        if box is None:
            box = (self.bounds[0], self.bounds[0])     # nothing to cut away for
        ground = None if self.has_statics else ground_grid(*self.bounds, self.reader.up_axis)
        return self.renderer.render(batches, self.camera, up_axis=self.reader.up_axis,
                                    bodies_box=box, light_box=self.bounds, ground=ground)


# ----------------------------------------------------------------------- writing


def _temp_beside(out: Path) -> Path:
    return out.with_name(f".{out.stem}.tmp-{os.getpid()}{out.suffix}")


def _atomic(out: Path, write) -> Path:
    """Run ``write(tmp)`` then move tmp over ``out``; remove tmp on any failure."""
    out = Path(out)
    if out.parent and not out.parent.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_beside(out)
    try:
        write(tmp)
        os.replace(tmp, out)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise PreviewError(f"{out}: cannot write ({exc.strerror or exc})") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return out


def save_png(image: np.ndarray, out) -> Path:
    """Write an (H, W, 3) uint8 picture to ``out`` as PNG, atomically."""
    from PIL import Image

    return _atomic(Path(out), lambda tmp: Image.fromarray(image).save(tmp, format="PNG"))


def _check_extension(out: Path, allowed) -> None:
    if out.suffix.lower() not in allowed:
        raise PreviewError(f"{out}: unknown extension {out.suffix!r} (use "
                           f"{', '.join(allowed)})")


def render_frame(path, out_png, *, frame: int | None = None, camera: str = "three-quarter",
                 size=DEFAULT_SIZE, samples: int = STILL_SAMPLES) -> Path:
    """Render time code ``frame`` (default: the last) of the bake at ``path`` to a PNG."""
    out = Path(out_png)
    _check_extension(out, STILL_EXTENSIONS)
    with Preview(path, size=size, camera=camera, samples=samples) as pv:
        return save_png(pv.image(frame), out)


def render_movie(path, out, *, frames: str | None = None, camera: str = "three-quarter",
                 size=DEFAULT_SIZE, fps: float | None = None, samples: int = MOVIE_SAMPLES,
                 progress=None) -> Path:
    """Render the bake (or the frames 'A:B') to an MP4 (H.264) or a GIF.

    ``fps`` defaults to the stage's framesPerSecond; ``progress(done, total)`` is called
    after each frame.
    """
    out = Path(out)
    _check_extension(out, MOVIE_EXTENSIONS)
    kind = out.suffix.lower()
    require("moderngl", "PIL", "av") if kind == ".mp4" else require()
    w, h = (int(v) for v in size)
    if kind == ".mp4" and (w % 2 or h % 2):
        raise PreviewError(f"--size {w}x{h}: an MP4 (H.264, yuv420p) needs an even width and "
                           f"height")
    with Preview(path, size=size, camera=camera, samples=samples) as pv:
        chosen = parse_frames(frames, pv.frames, pv.path.name)
        rate = float(fps or pv.reader.fps)

        def pictures():
            for k, f in enumerate(chosen):
                yield pv.image(f)
                if progress is not None:
                    progress(k + 1, len(chosen))

        writer = _write_mp4 if kind == ".mp4" else _write_gif
        return _atomic(out, lambda tmp: writer(tmp, pictures(), rate))


def _write_mp4(tmp: Path, pictures, fps: float) -> None:
    from fractions import Fraction

    import av

    with av.open(str(tmp), mode="w", format="mp4") as container:
        stream = None
        for img in pictures:
            if stream is None:
                stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
                stream.height, stream.width = img.shape[:2]
                stream.pix_fmt = "yuv420p"
                stream.options = {"crf": "20", "preset": "veryfast"}
            frame = av.VideoFrame.from_ndarray(img, format="rgb24")
            for packet in stream.encode(frame):
                container.mux(packet)
        if stream is not None:
            for packet in stream.encode():
                container.mux(packet)


def _write_gif(tmp: Path, pictures, fps: float) -> None:
    from PIL import Image

    frames = [Image.fromarray(img).quantize(colors=256, method=Image.Quantize.MEDIANCUT)
              for img in pictures]
    duration = max(int(round(1000.0 / fps)), 20)
    frames[0].save(tmp, format="GIF", save_all=True, append_images=frames[1:],
                   duration=duration, loop=0, optimize=False)


def contact_sheet(paths, out_png, *, labels=None, columns: int | None = None,
                  tile=(640, 360), camera: str = "three-quarter", frame: int | None = None) -> Path:
    """A PNG grid of each bake's last frame (or ``frame``), labelled (default: file names).

    For `dempipe wedge`: one tile per variant, ``columns`` across (default: a near-square
    grid). A bake that cannot be read raises PreviewError naming it.
    """
    from PIL import Image, ImageDraw, ImageFont

    paths = [Path(p) for p in paths]
    if not paths:
        raise PreviewError("contact sheet: no bakes given")
    labels = [p.stem for p in paths] if labels is None else [str(s) for s in labels]
    if len(labels) != len(paths):
        raise PreviewError(f"contact sheet: {len(labels)} labels for {len(paths)} bakes")
    out = Path(out_png)
    _check_extension(out, STILL_EXTENSIONS)
    require()
    w, h = (int(v) for v in tile)
    cols = columns or math.ceil(math.sqrt(len(paths)))
    rows = math.ceil(len(paths) / cols)
    sheet = Image.new("RGB", (cols * w, rows * h), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    try:
        font = ImageFont.load_default(size=max(12, h // 18))
    except TypeError:       # Pillow < 10.1: a fixed-size bitmap font
        font = ImageFont.load_default()
    renderer = None
    try:
        for k, (p, label) in enumerate(zip(paths, labels)):
            pv = Preview(p, size=(w, h), camera=camera, renderer=renderer)
            renderer = pv.renderer
            img = pv.image(frame)
            x, y = (k % cols) * w, (k // cols) * h
            sheet.paste(Image.fromarray(img), (x, y))
            draw.rectangle([x, y, x + w - 1, y + h - 1], outline=(255, 255, 255), width=2)
            tb = draw.textbbox((0, 0), label, font=font)
            draw.rectangle([x + 4, y + 4, x + 12 + tb[2] - tb[0], y + 12 + tb[3] - tb[1]],
                           fill=(255, 255, 255))
            draw.text((x + 8 - tb[0], y + 8 - tb[1]), label, fill=(0, 0, 0), font=font)
    finally:
        if renderer is not None:
            renderer.release()
    return save_png(np.asarray(sheet), out)
