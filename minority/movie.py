"""Movies of a view's frames: an MP4 (H.264, yuv420p: browsers and players open it) through
the ffmpeg that the imageio-ffmpeg wheel ships, and a small animated WebP for a README or a
web page (Pillow).

Frames are PNG files, PNG bytes or RGB(A) arrays [h, w, 3|4] uint8, given in step order.
The frame rate rule: one movie frame per rendered frame, at a fixed rate (`fps`, default
10). A view's schedule may change cadence between windows, so movie time is not simulated
time: a fast window's frames play as long as a slow window's.

Sizes: H.264 in yuv420p needs even sides. Every frame is padded (never cropped, never
scaled) at its right and bottom edges to the largest even width and height among the view's
frames, repeating its edge pixels, so a 49 x 37 view becomes a 50 x 38 movie whose extra row
and column copy their neighbours. The animation is scaled down to ANIMATION_WIDTH px wide
(never up), takes at most ANIMATION_FRAMES frames evenly spread over the view's frames and
shows each for as long as the frames it stands for last in the MP4, so both play the run in
the same time.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

DEFAULT_FPS = 10.0  # movie frames per second: one per rendered frame
ANIMATION_WIDTH = 320  # px
ANIMATION_FRAMES = 40  # at most
ANIMATION_MAX_BYTES = 1_000_000
ANIMATION_QUALITIES = (80, 60, 40, 25)  # WebP quality tried in turn until under the bound
MP4_QUALITY = 7  # imageio-ffmpeg's 1-10 scale: libx264 -crf 15 (mean error under 1 of 255)

Source = Path | str | bytes | np.ndarray  # a PNG file, PNG bytes, or [h, w, 3|4] uint8


class MovieError(ValueError):
    """Frames a movie cannot be made of (none, or not an image)."""


@dataclass
class Movie:
    """What write_movies wrote for one view."""

    view: str
    mp4: Path
    frames: int
    size: tuple[int, int]  # the movie's width, height (px): the frames' padded to even
    fps: float
    animation: Path | None = None
    animation_frames: int = 0
    animation_size: tuple[int, int] = (0, 0)  # px
    animation_bytes: int = 0

    @property
    def duration_s(self) -> float:
        return self.frames / self.fps

    def line(self) -> str:
        w, h = self.size
        text = (f"movie {self.view}: {self.frames} frames, {w}x{h}, {self.duration_s:.1f} s "
                f"at {self.fps:g} fps -> {self.mp4}")
        if self.animation is not None:
            aw, ah = self.animation_size
            text += (f"; animation {self.animation_frames} frames, {aw}x{ah}, "
                     f"{self.animation_bytes / 1e3:.0f} kB -> {self.animation}")
        return text


def rgb(source: Source) -> np.ndarray:
    """The frame as [h, w, 3] uint8 RGB (alpha dropped, gray expanded)."""
    if isinstance(source, np.ndarray):
        a = np.asarray(source)
        if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] not in (3, 4):
            raise MovieError(f"a frame array must be [h, w, 3 or 4] uint8, not "
                             f"{list(a.shape)} {a.dtype}")
        return np.ascontiguousarray(a[:, :, :3])
    with _open(source) as im:
        return np.asarray(im.convert("RGB"))


def image_size(source: Source) -> tuple[int, int]:
    """(width, height) px, from the PNG header alone for files and bytes."""
    if isinstance(source, np.ndarray):
        return int(source.shape[1]), int(source.shape[0])
    with _open(source) as im:
        return im.size


def _open(source: Path | str | bytes) -> Image.Image:
    try:
        return Image.open(io.BytesIO(source) if isinstance(source, bytes) else source)
    except OSError as exc:  # PIL.UnidentifiedImageError is an OSError
        where = "PNG bytes" if isinstance(source, bytes) else str(source)
        raise MovieError(f"{where}: not an image ({exc})") from exc


def even(n: int) -> int:
    return n + n % 2


def padded(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """`image` [h, w, 3] grown to [height, width, 3] by repeating its last row and column."""
    h, w = image.shape[:2]
    if w > width or h > height:
        raise MovieError(f"a {w}x{h} frame does not fit a {width}x{height} movie")
    if (w, h) == (width, height):
        return image
    return np.pad(image, ((0, height - h), (0, width - w), (0, 0)), mode="edge")


def movie_size(frames: Sequence[Source]) -> tuple[int, int]:
    """The even (width, height) px that holds every frame."""
    if not frames:
        raise MovieError("no frames")
    sizes = [image_size(f) for f in frames]
    return even(max(w for w, _ in sizes)), even(max(h for _, h in sizes))


def _writable(path: Path) -> Path:
    """`path`, its directory made and the file opened for writing once: an unwritable path
    fails here (OSError) rather than inside ffmpeg."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb"):
        pass
    return path


def write_mp4(frames: Sequence[Source], path: Path, fps: float = DEFAULT_FPS) -> tuple[int, int]:
    """Encode `frames` (step order) as an H.264 yuv420p MP4 at `fps` frames per second, one
    movie frame per frame; returns its (width, height) px. OSError when `path` cannot be
    written, RuntimeError when ffmpeg fails, MovieError for frames it cannot use."""
    import imageio_ffmpeg

    if not fps > 0:
        raise MovieError(f"fps must be positive, not {fps}")
    width, height = movie_size(frames)
    path = _writable(path)
    writer = imageio_ffmpeg.write_frames(
        str(path), (width, height), fps=fps, codec="libx264", quality=MP4_QUALITY,
        macro_block_size=1,  # the frames are padded to even sides: ffmpeg must not rescale
        ffmpeg_log_level="error", output_params=["-movflags", "+faststart"])
    writer.send(None)  # start ffmpeg
    try:
        for frame in frames:
            writer.send(padded(rgb(frame), width, height))
    except BaseException as exc:
        writer.close()
        path.unlink(missing_ok=True)  # no half movie left behind
        if isinstance(exc, OSError):  # imageio-ffmpeg's: ffmpeg stopped reading (its stderr)
            raise RuntimeError(f"{path}: ffmpeg failed: {str(exc).splitlines()[0]}") from exc
        raise
    writer.close()  # waits for ffmpeg to finish the file
    if path.stat().st_size == 0:
        raise RuntimeError(f"{path}: ffmpeg wrote nothing (its messages are above)")
    return width, height


def pick(n: int, most: int) -> list[int]:
    """At most `most` indices spread evenly over range(n), the first and last included."""
    if n <= most:
        return list(range(n))
    if most < 2:
        return [0][:most]
    return sorted({round(i * (n - 1) / (most - 1)) for i in range(most)})


def write_animation(frames: Sequence[Source], path: Path, fps: float = DEFAULT_FPS,
                    width: int = ANIMATION_WIDTH, most: int = ANIMATION_FRAMES,
                    max_bytes: int = ANIMATION_MAX_BYTES) -> tuple[int, tuple[int, int], int]:
    """An animated WebP (looping) of at most `most` of `frames`, scaled to `width` px wide,
    lasting as long as the MP4 of all of them at `fps`; its quality is lowered, then its
    frames halved, until it holds under `max_bytes`. Returns (frames, (width, height) px,
    bytes)."""
    if not frames:
        raise MovieError("no frames")
    if not fps > 0:
        raise MovieError(f"fps must be positive, not {fps}")
    full_w, full_h = movie_size(frames)
    scale = min(1.0, width / full_w)
    size = (max(1, round(full_w * scale)), max(1, round(full_h * scale)))
    path = _writable(path)
    while True:
        chosen = pick(len(frames), most)
        images = [Image.fromarray(padded(rgb(frames[i]), full_w, full_h)).resize(
            size, Image.Resampling.LANCZOS) for i in chosen]
        # each picture shows until the next one's time in the MP4 (ms)
        ends = chosen[1:] + [len(frames)]
        durations = [max(1, round((e - s) * 1000 / fps)) for s, e in zip(chosen, ends,
                                                                         strict=True)]
        for quality in ANIMATION_QUALITIES:
            images[0].save(path, format="WEBP", save_all=True, append_images=images[1:],
                           duration=durations, loop=0, quality=quality, method=4)
            nbytes = path.stat().st_size
            if nbytes <= max_bytes:
                return len(images), size, nbytes
        if most <= 2:
            raise MovieError(f"{path}: an animation of {size[0]}x{size[1]} px does not fit "
                             f"in {max_bytes} bytes")
        most = max(2, most // 2)


def write_movies(views: Mapping[str, Sequence[Source]], folder: Path,
                 fps: float = DEFAULT_FPS, animation: bool = True,
                 progress: Callable[[str], None] | None = None) -> list[Movie]:
    """folder/{view}.mp4 (and, with `animation`, folder/{view}.webp) for each view with
    frames, in step order; a line to `progress` before each movie. A view with no frames is said to
    `progress` and skipped; MovieError when no view has any."""
    if not any(views.values()):
        raise MovieError("no frames to make movies of" + (
            f" (views {', '.join(views)})" if views else ""))
    movies = []
    for view, frames in views.items():
        if not frames:
            if progress is not None:
                progress(f"movie {view}: no frames, no movie")
            continue
        mp4 = folder / f"{view}.mp4"
        webp = folder / f"{view}.webp" if animation else None
        if progress is not None:
            progress(f"movie {view}: encoding {len(frames)} frames -> {mp4}"
                     + (f", {webp.name}" if webp else ""))
        movie = Movie(view, mp4, len(frames), write_mp4(frames, mp4, fps), fps, webp)
        if webp is not None:
            (movie.animation_frames, movie.animation_size,
             movie.animation_bytes) = write_animation(frames, webp, fps)
        movies.append(movie)
    return movies


def frame_folders(run_dir: Path) -> dict[str, list[Path]]:
    """The PNG frames under run_dir/{view}/{step:06d}.png (the layout of `minority serve
    --out` and `minority replay --out`), per view in step order."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise MovieError(f"{run_dir}: no such directory")
    views = {d.name: sorted(d.glob("*.png"), key=_step_of) for d in sorted(run_dir.iterdir())
             if d.is_dir()}
    return {name: frames for name, frames in views.items() if frames}


def _step_of(png: Path) -> tuple[int, str]:
    return (int(png.stem), png.name) if png.stem.isdigit() else (-1, png.name)
