"""Depth images to 8-bit grey levels, and a tiled PNG of many of them for inspection (paper Fig. 8)."""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["to_uint8", "tile", "save_png"]


def to_uint8(images: ArrayLike, *, background: float | None = None) -> np.ndarray:
    """Stretch each image linearly to the full 0-255 range.

    Parameters
    ----------
    images : (n, H, W) or (H, W) float; NaN marks background pixels
    background : grey level given to NaN pixels before stretching, as a height; None (default) uses
        the image's lowest finite value (NaN pixels look like the farthest surface seen).

    Returns
    -------
    uint8 array of the same shape: ``round(255 (x - min) / (max - min))`` per image, where min and max
    are over that image's pixels (after filling NaN). A constant image maps to all zeros; an image with
    no finite pixel and ``background=None`` maps to all zeros.
    """
    a = np.asarray(images, dtype=np.float64)
    if a.ndim not in (2, 3):
        raise ValueError(f"images must have shape (n, H, W) or (H, W), got {a.shape}")
    single = a.ndim == 2
    a = a[None] if single else a.copy()
    nan = np.isnan(a)
    if nan.any():
        if background is None:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN images: handled just below
                fill = np.nanmin(a, axis=(1, 2))
            fill = np.where(np.isnan(fill), 0.0, fill)
            a = np.where(nan, fill[:, None, None], a)
        else:
            a = np.where(nan, float(background), a)
    if not np.all(np.isfinite(a)):
        raise ValueError("images contain infinite values; give finite heights (or NaN for background)")
    lo = a.min(axis=(1, 2), keepdims=True)
    span = a.max(axis=(1, 2), keepdims=True) - lo
    scale = np.divide(255.0, span, out=np.zeros_like(span), where=span > 0)
    out = np.rint((a - lo) * scale).clip(0, 255).astype(np.uint8)
    return out[0] if single else out


def tile(images: ArrayLike, *, columns: int | None = None, pad: int = 1, pad_value: int = 255) -> np.ndarray:
    """Arrange (n, H, W) uint8 images on a grid (row-major), ``pad`` pixels apart. Returns a 2-D uint8 array."""
    a = np.asarray(images)
    if a.ndim != 3 or a.dtype != np.uint8:
        raise ValueError(f"tile expects (n, H, W) uint8 images, got shape {a.shape} dtype {a.dtype}")
    n, h, w = a.shape
    if n == 0:
        raise ValueError("no images to tile (n = 0)")
    cols = int(columns) if columns is not None else int(np.ceil(np.sqrt(n)))
    if cols < 1:
        raise ValueError(f"columns must be >= 1, got {columns!r}")
    if pad < 0:
        raise ValueError(f"pad must be >= 0, got {pad!r}")
    rows = -(-n // cols)
    grid = np.full((rows * (h + pad) + pad, cols * (w + pad) + pad), pad_value, dtype=np.uint8)
    for k in range(n):
        r, c = divmod(k, cols)
        y, x = pad + r * (h + pad), pad + c * (w + pad)
        grid[y : y + h, x : x + w] = a[k]
    return grid


def save_png(
    images: ArrayLike,
    path: str | Path,
    *,
    columns: int | None = None,
    scale: int = 8,
    pad: int = 1,
    background: float | None = None,
) -> np.ndarray:
    """Save depth images as one PNG: each image stretched to 0-255 (`to_uint8`), tiled, enlarged.

    Parameters
    ----------
    images : (n, H, W) or (H, W) float heights (NaN = background), or uint8 grey levels (kept as is)
    path : output file (``.png``)
    columns : images per row of the grid (default about sqrt(n))
    scale : integer enlargement (nearest neighbour) so that 21x21 images stay readable
    pad : white pixels between tiles (before enlargement)
    background : see `to_uint8`

    Returns
    -------
    The written image, 2-D uint8.
    """
    import cv2

    a = np.asarray(images)
    if a.ndim == 2:
        a = a[None]
    g = a if a.dtype == np.uint8 else to_uint8(a, background=background)
    grid = tile(g, columns=columns, pad=pad)
    if int(scale) < 1:
        raise ValueError(f"scale must be an integer >= 1, got {scale!r}")
    grid = np.kron(grid, np.ones((int(scale), int(scale)), dtype=np.uint8))
    path = Path(path)
    if not cv2.imwrite(str(path), grid):
        raise ValueError(f"could not write a PNG to {str(path)!r} (check the folder exists and the suffix is .png)")
    return grid
