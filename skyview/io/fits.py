"""FITS images, as astronomy cameras and capture programs write them.

`read_fits` returns the image as skyview holds every image: a 2-D array whose row 0 is the top of
the picture (OpenCV's and PNG's order). The FITS standard stores the bottom row first, and a
capture program that follows it shows the sky the right way round in DS9; many others write the
sensor's rows top-down and say so with `ROWORDER = 'TOP-DOWN'`. So the rows are turned over unless
the header says TOP-DOWN; when the header says nothing (`ROWORDER` absent), `row_order_declared`
is False. A file read the wrong way up is a mirror image of the sky (its edge ratios, the wrong
handedness): the blind searches find it so and report it with its rows turned over (`rows_reversed`); a
method at an FOV given does not, so the pipeline tries the other order too if the first does not solve.

Read with astropy (BZERO/BSCALE applied, tile-compressed `.fz` included): the first HDU with a 2-D
image, or a colour cube of 3 or 4 planes (averaged to grey). A raw colour sensor (`BAYERPAT`) is
converted to grey by OpenCV's demosaicing. The pixel count is checked from the header before any
data is read.
"""

from __future__ import annotations

import contextlib
import io
import os
import warnings
from pathlib import Path

import cv2
import numpy as np

from skyview.core.errors import BadInput

FITS_MAGIC = b"SIMPLE  ="
# OpenCV names a Bayer pattern by the second row's second and third pixels: a sensor's RGGB is its BG
_BAYER_TO_GRAY = {"RGGB": cv2.COLOR_BayerBG2GRAY, "BGGR": cv2.COLOR_BayerRG2GRAY,
                  "GRBG": cv2.COLOR_BayerGB2GRAY, "GBRG": cv2.COLOR_BayerGR2GRAY}


@contextlib.contextmanager
def _quiet():
    """astropy's warnings about a file's header (the error that follows says what matters)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


def is_fits(head: bytes) -> bool:
    """True when the bytes start a FITS file."""
    return bytes(head[: len(FITS_MAGIC)]) == FITS_MAGIC


def read_fits(path: str | os.PathLike, max_pixels: int, content: bytes | None = None) -> tuple[np.ndarray, bool]:
    """(image with row 0 at the top, whether the file declared its row order) of a FITS file, or of its bytes
    `content` (an upload: `path` is then its name, for the messages).

    BadInput with one line for a file astropy cannot read, one with no image, a data cube that is
    not a colour image, and an image over `max_pixels` pixels (checked before reading the data).
    """
    from astropy.io import fits  # astropy is a dependency; imported here to keep the solve path's start short

    p = Path(path)
    try:
        # the data is read only when asked for, after the size check (memmap cannot apply BZERO)
        with _quiet(), fits.open(p if content is None else io.BytesIO(content), memmap=False,
                                 lazy_load_hdus=True) as hdul:
            for hdu in hdul:
                if not getattr(hdu, "is_image", False):
                    continue
                header = hdu.header
                naxis = int(header.get("ZNAXIS", header.get("NAXIS", 0)))
                shape = [int(header.get(f"ZNAXIS{k}", header.get(f"NAXIS{k}", 0))) for k in range(1, naxis + 1)]
                if naxis < 2 or min(shape[:2]) == 0:
                    continue
                if naxis > 3 or (naxis == 3 and shape[2] not in (3, 4)):
                    raise BadInput(f"{p} holds a data cube of shape {tuple(reversed(shape))}, not an image "
                                   "(2-D, or 3 or 4 colour planes)")
                if shape[0] * shape[1] > max_pixels:
                    raise BadInput(f"{p} is {shape[0]} x {shape[1]} pixels ({shape[0] * shape[1] / 1e6:.0f} MP), "
                                   f"more than the {max_pixels / 1e6:.0f} MP skyview decodes (set "
                                   "SKYVIEW_MAX_PIXELS to raise the limit)")
                data = np.asarray(hdu.data)
                img = _to_grey(data, str(header.get("BAYERPAT", "")).strip().upper())
                order = str(header.get("ROWORDER", "")).strip().upper()
                if order != "TOP-DOWN":
                    img = img[::-1]
                return np.ascontiguousarray(img), order in ("TOP-DOWN", "BOTTOM-UP")
    except BadInput:
        raise
    except (OSError, ValueError, TypeError, IndexError, KeyError) as exc:
        raise BadInput(f"{p} is not a FITS file astropy can read ({type(exc).__name__}: "
                       f"{str(exc).splitlines()[0] if str(exc) else 'damaged'})") from None
    raise BadInput(f"{p} is a FITS file with no image in it")


def _to_grey(data: np.ndarray, bayer: str) -> np.ndarray:
    """A FITS image's data as one grey plane (native byte order: OpenCV and numpy's fast paths)."""
    if data.dtype.byteorder not in ("=", "|"):
        data = data.astype(data.dtype.newbyteorder("="))
    if data.ndim == 3:
        return data.astype(np.float32).mean(axis=0)
    if bayer in _BAYER_TO_GRAY and data.dtype in (np.uint8, np.uint16):
        return cv2.cvtColor(np.ascontiguousarray(data), _BAYER_TO_GRAY[bayer])
    if data.dtype.kind in "ui" and data.dtype.itemsize <= 2:
        return data
    return data.astype(np.float32)


def undeclared_row_order(path: str | os.PathLike) -> bool:
    """True for a FITS file whose header does not say its row order (no ROWORDER keyword): its rows
    may be either way up. False for any other file."""
    return row_order(path) == ""


def row_order(path: str | os.PathLike) -> str | None:
    """The ROWORDER of a FITS file's image ("" when the header has none); None for any other file.
    `read_fits` turns the rows over unless it is "TOP-DOWN"."""
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            if not is_fits(fh.read(len(FITS_MAGIC))):
                return None
        from astropy.io import fits

        with _quiet(), fits.open(p, memmap=False, lazy_load_hdus=True) as hdul:
            for hdu in hdul:
                if getattr(hdu, "is_image", False) and int(hdu.header.get("NAXIS", 0)) >= 2:
                    order = str(hdu.header.get("ROWORDER", "")).strip().upper()
                    return order if order in ("TOP-DOWN", "BOTTOM-UP") else ""
    except (OSError, ValueError, TypeError, IndexError, KeyError):
        return None
    return None
