"""Reading and writing images: linear EXR for radiance, sRGB PNG for people."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import ImageError


def write_exr(image: np.ndarray, path: str | Path) -> None:
    """Writes (H, W, 3) linear radiance as a float32 OpenEXR file."""
    import mitsuba as mi

    mi.Bitmap(np.ascontiguousarray(image, np.float32), mi.Bitmap.PixelFormat.RGB).write(str(path))


def read_exr(path: str | Path) -> np.ndarray:
    """Reads an EXR (or any format Mitsuba reads) as (H, W, C) float32 linear values."""
    import mitsuba as mi

    path = Path(path)
    if not path.is_file():
        raise ImageError(f"image not found: {path}")
    try:
        bmp = mi.Bitmap(str(path))
    except Exception as err:  # Mitsuba raises RuntimeError subclasses on unreadable files
        raise ImageError(f"cannot read image {path}: {str(err).splitlines()[0]}") from None
    arr = np.array(bmp.convert(component_format=mi.Struct.Type.Float32, srgb_gamma=False), np.float32)
    return arr if arr.ndim == 3 else arr[..., None]


def to_srgb8(image: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Linear radiance -> 8-bit sRGB, after scaling by 2^exposure."""
    x = np.clip(np.asarray(image, np.float64) * 2.0**exposure, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255).astype(np.uint8)


def png_bytes(image: np.ndarray, exposure: float = 0.0) -> bytes:
    """An sRGB PNG of linear radiance, as bytes."""
    import mitsuba as mi

    stream = mi.MemoryStream()
    mi.Bitmap(to_srgb8(image, exposure), mi.Bitmap.PixelFormat.RGB).write(stream, mi.Bitmap.FileFormat.PNG)
    return stream.raw_buffer()


def write_png(image: np.ndarray, path: str | Path, exposure: float = 0.0) -> None:
    Path(path).write_bytes(png_bytes(image, exposure))


def latlong_directions(width: int) -> np.ndarray:
    """(width // 2, width, 3) unit directions at the texel centres of a lat-long image: row j
    at theta = pi (j + 0.5) / h from +y, column i at phi = 2 pi (i + 0.5) / w, and
    d = (sin theta sin phi, cos theta, -sin theta cos phi) (api.md, the field's ``background``)."""
    h = width // 2
    theta = np.pi * (np.arange(h) + 0.5) / h
    phi = 2 * np.pi * (np.arange(width) + 0.5) / width
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    return np.stack(np.broadcast_arrays(st * np.sin(phi), ct, -st * np.cos(phi)), axis=-1)
