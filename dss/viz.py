"""Turning (V, H, W, C) renders into PNG files and grids (no display needed)."""

from __future__ import annotations

import io
import math
import os
from pathlib import Path

import numpy as np
import torch

from .io_utils import atomic_write_bytes

__all__ = ["to_uint8", "image_grid", "labelled_rows", "save_png", "save_grid", "colorize_normals", "colorize_depth"]


def to_uint8(img, lo: float = 0.0, hi: float = 1.0) -> np.ndarray:
    """(H, W, C) float -> (H, W, 3) uint8; one channel is repeated, values clipped to [lo, hi]."""
    a = img.detach().cpu().float().numpy() if isinstance(img, torch.Tensor) else np.asarray(img, np.float32)
    if a.ndim == 2:
        a = a[..., None]
    if a.shape[-1] == 1:
        a = np.repeat(a, 3, -1)
    a = (np.clip((a - lo) / max(hi - lo, 1e-12), 0, 1) * 255 + 0.5).astype(np.uint8)
    return a[..., :3]


def image_grid(images, ncols: int | None = None, pad: int = 2, pad_value: int = 255) -> np.ndarray:
    """Tile V images (V, H, W, 3) uint8 into one (rows*H, cols*W, 3) uint8 array."""
    imgs = [np.asarray(i) for i in images]
    V = len(imgs)
    if V == 0:
        raise ValueError("no images to tile")
    H, W = imgs[0].shape[:2]
    ncols = ncols or int(math.ceil(math.sqrt(V)))
    nrows = int(math.ceil(V / ncols))
    out = np.full((nrows * (H + pad) - pad, ncols * (W + pad) - pad, 3), pad_value, np.uint8)
    for k, im in enumerate(imgs):
        r, c = divmod(k, ncols)
        out[r * (H + pad): r * (H + pad) + H, c * (W + pad): c * (W + pad) + W] = im
    return out


def labelled_rows(rows, labels, pad: int = 4, label_width: int | None = None, font_size: int = 14) -> np.ndarray:
    """Rows of images with a label left of each row, as one (H', W', 3) uint8 picture.

    ``rows``: one (V, H, W, C) float tensor or array in [0, 1] per row (rows may have different
    V; all images the same H, W); ``labels``: one string per row. Pillow draws the text, so no
    plotting library is imported (matplotlib's import alone takes about a second).
    """
    from PIL import Image, ImageDraw, ImageFont

    if len(rows) != len(labels) or not rows:
        raise ValueError(f"labelled_rows: {len(rows)} rows and {len(labels)} labels")
    tiles = [[to_uint8(im) for im in row] for row in rows]
    H, W = tiles[0][0].shape[:2]
    font = ImageFont.load_default(size=font_size)
    if label_width is None:
        label_width = max(int(ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength(t, font=font)) for t in labels) + 2 * pad
    ncols = max(len(r) for r in tiles)
    out = np.full((len(tiles) * (H + pad) + pad, label_width + ncols * (W + pad) + pad, 3), 255, np.uint8)
    for r, row in enumerate(tiles):
        y = pad + r * (H + pad)
        for c, im in enumerate(row):
            x = label_width + pad + c * (W + pad)
            out[y:y + H, x:x + W] = im
    canvas = Image.fromarray(out)
    draw = ImageDraw.Draw(canvas)
    for r, text in enumerate(labels):
        draw.text((pad, pad + r * (H + pad) + H // 2), text, fill=(0, 0, 0), font=font, anchor="lm")
    return np.asarray(canvas)


def save_png(path: str | os.PathLike, img_u8: np.ndarray) -> Path:
    """Write a uint8 (H, W, 3) image as PNG, atomically (Pillow's encoder)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(img_u8, np.uint8)).save(buf, format="png")
    return atomic_write_bytes(path, buf.getvalue())


def save_grid(path, images: torch.Tensor, ncols: int | None = None, lo: float = 0.0, hi: float = 1.0) -> Path:
    """Save (V, H, W, C) float images as one PNG grid."""
    return save_png(path, image_grid([to_uint8(i, lo, hi) for i in images], ncols))


def colorize_normals(images: torch.Tensor, mask: torch.Tensor | None = None, background: float = 1.0) -> torch.Tensor:
    """Map normal renders in [-1, 1] to RGB in [0, 1]; background where ``mask`` is False."""
    out = images * 0.5 + 0.5
    if mask is not None:
        out = torch.where(mask[..., None], out, torch.full_like(out, background))
    return out


def colorize_depth(inv_depth: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Inverse-depth renders (V, H, W, 1) -> grey levels scaled per view to [0.15, 1] (near = bright)."""
    out = torch.zeros_like(inv_depth)
    for v in range(inv_depth.shape[0]):
        m = mask[v]
        if m.any():
            d = inv_depth[v][m]
            lo, hi = d.min(), d.max()
            out[v][m] = 0.15 + 0.85 * (d - lo) / (hi - lo).clamp_min(1e-12)
    return out
