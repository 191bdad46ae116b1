"""Text for the overlay (`render_server/overlay.py`): the font and its sizes, tick and time
label text, and the per-frame time text, laid out glyph by glyph from bitmaps rendered once
per font size and blended into the frame by a numba loop.

Sizes are in px: the font grows with the image's height (FONT_PX_PER_HEIGHT) within FONT_PX;
text has a halo (halo_px wide) in the background colour, readable over particles.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from functools import cache

import numpy as np
from numba import njit
from PIL import Image, ImageDraw, ImageFont

FONT_PX_PER_HEIGHT = 1 / 48  # font size (px) per image height (px): 16 px at 768
FONT_PX = (8, 40)  # smallest and largest font size, px


@dataclass(frozen=True)
class TimeText:
    """Where and how the per-frame time text goes."""

    x: int  # px, left edge of the text box
    y: int  # px, top edge
    font_px: int
    ink: np.ndarray  # [3] float32 in [0, 255]
    halo: np.ndarray  # [3] float32 in [0, 255]


def time_label(step: int, time_s: float) -> str:
    """The text of the time annotation, e.g. "t = 0.195 s · step 1652"."""
    return f"t = {time_s:.3f} s · step {step}"


def tick_text(value: float) -> str:
    """A colorbar tick's label: 3 significant digits."""
    return f"{value:.3g}"


def font_px(height: int) -> int:
    return int(min(max(round(height * FONT_PX_PER_HEIGHT), FONT_PX[0]), FONT_PX[1]))


@cache
def font(size: int) -> ImageFont.FreeTypeFont:
    """Pillow's built-in scalable font at `size` px (no font file needed)."""
    return ImageFont.load_default(size=size)


def halo_px(size: int) -> int:
    return max(1, size // 8)


# --- time text: glyphs rendered once, a string laid out per frame ------------------------


class Glyphs:
    """Bitmaps of one font size's characters, rendered on first use into two atlases (fill
    and halo coverage, [line height, width] float32 in [0, 1]), with each character's place
    in them and its advance (px). Text is laid out glyph by glyph (no kerning)."""

    def __init__(self, size: int):
        self.size = size
        self.pad = halo_px(size) + 2  # px around a glyph: its halo and overhangs
        ascent, descent = font(size).getmetrics()
        self.line_h = ascent + descent + 2 * self.pad
        self.fill = np.zeros((self.line_h, 0), np.float32)
        self.halo = np.zeros((self.line_h, 0), np.float32)
        self.where: dict[str, tuple[int, int, float]] = {}  # char -> atlas x, width, advance
        self._lock = threading.Lock()

    def _add(self, ch: str) -> None:
        f = font(self.size)
        advance = f.getlength(ch)
        box = (math.ceil(advance) + 2 * self.pad, self.line_h)
        masks = []
        for stroke in (0, halo_px(self.size)):
            img = Image.new("L", box, 0)
            ImageDraw.Draw(img).text((self.pad, self.pad), ch, font=f, fill=255,
                                     stroke_width=stroke, stroke_fill=255)
            masks.append(np.asarray(img, np.float32) / 255.0)
        x = self.fill.shape[1]
        self.fill = np.concatenate([self.fill, masks[0]], axis=1)  # new arrays: a reader
        self.halo = np.concatenate([self.halo, masks[1]], axis=1)  # keeps the old ones
        self.where[ch] = (x, box[0], advance)

    def layout(self, text: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                         np.ndarray]:
        """For each character of `text`: its atlas x, its width and its x in the text box
        (int64 [m] each, px), with the fill and halo atlases they index."""
        missing = set(text) - self.where.keys()
        if missing:
            with self._lock:
                for ch in sorted(missing - self.where.keys()):
                    self._add(ch)
        src, width, dst, x = [], [], [], 0.0
        for ch in text:
            at, w, advance = self.where[ch]
            src.append(at)
            width.append(w)
            dst.append(round(x))
            x += advance
        return (np.array(src, np.int64), np.array(width, np.int64), np.array(dst, np.int64),
                self.fill, self.halo)


@cache
def glyphs(size: int) -> Glyphs:
    return Glyphs(size)


@njit(cache=True, nogil=True)
def _draw_glyphs(image, y0, x0, fill, halo, src, width, dst, ink, halo_rgb):
    """Blend laid-out glyphs into image [h, w, 3] uint8 at (x0, y0) px: every halo, then
    every fill, clipped to the image."""
    h, w = image.shape[0], image.shape[1]
    for layer in range(2):
        mask = halo if layer == 0 else fill
        colour = halo_rgb if layer == 0 else ink
        for g in range(src.shape[0]):
            for r in range(mask.shape[0]):
                y = y0 + r
                if y < 0 or y >= h:
                    continue
                for c in range(width[g]):
                    x = x0 + dst[g] + c
                    a = mask[r, src[g] + c]
                    if x < 0 or x >= w or a <= 0.0:
                        continue
                    for k in range(3):
                        image[y, x, k] = np.uint8(image[y, x, k] * (1.0 - a) + colour[k] * a
                                                  + 0.5)


def draw_time(image: np.ndarray, style: TimeText, text: str) -> None:
    """Blend `text` (halo, then ink) into image [h, w, 3] uint8 at the style's place,
    clipped to the image."""
    src, width, dst, fill, halo = glyphs(style.font_px).layout(text)
    _draw_glyphs(image, style.y, style.x, fill, halo, src, width, dst, style.ink, style.halo)
