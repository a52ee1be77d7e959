"""A solution as a FITS WCS (TAN, ARC or ZEA, with SIP terms for the fitted radial distortion), through astropy.

The header opens in DS9, astropy and the astrometry.net tools. Conventions (docs/conventions.md):
CRVAL is the boresight RA/Dec (degrees); CRPIX the principal point + 1 (FITS pixels are 1-based);
CD the 2x2 linear part in degrees per pixel, with the roll and the parity of the camera frame (x
right, y down); the radial distortion x_d = x (1 + k1 r^2 + k2 r^4) becomes the SIP polynomials A, B
(pixel -> intermediate: distorted offsets (u, v) from CRPIX map to undistorted (u + A, v + B)),
with the inverse AP, BP fitted on a grid, so `all_world2pix` lands on the centroids. A fisheye
(`skyview.core.camera`) takes the projection its lens is: ARC for the equidistant (the radius in
intermediate degrees is the off-axis angle), ZEA for the equisolid (2 sin(angle / 2)); the same CD
scales both, and its distortion in the off-axis angle becomes SIP terms the same way.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from skyview.core.camera import Camera
from skyview.core.errors import BadInput

SIP_ORDER = 5  # r^4 terms of the inverse need order 5


def solution_wcs(R: np.ndarray, camera: Camera, *, rows_reversed: bool = False):
    """astropy.wcs.WCS for attitude R (v_cam = R v_icrs) and the camera (with k1, k2 as SIP).

    rows_reversed: the WCS of the file the image was read from with its rows turned over (a FITS
    file stored bottom row first, as the standard has it: file row = height - 1 - image row).
    """
    try:
        from astropy.wcs import WCS, Sip
    except ImportError:
        raise BadInput("writing a WCS needs astropy: pip install astropy") from None
    from skyview.core.attitude import east_north
    from skyview.core.catalog import vec_to_radec

    R = np.asarray(R, dtype=np.float64)
    ra, dec = vec_to_radec(R[2])
    # intermediate world coordinates (degrees) of the gnomonic projection at the boresight, in the
    # local east/north frame: xi to the east, eta to the north

    e, n = east_north(R[2])
    # camera x / y axes (rows 0, 1 of R) expressed in (east, north): a unit step in normalised camera
    # x moves (x . e, x . n) in (xi, eta) radians at the tangent point
    M = np.array([[R[0] @ e, R[1] @ e], [R[0] @ n, R[1] @ n]])  # (xi, eta) = M (x, y)
    scale = np.diag([1.0 / camera.fx, 1.0 / camera.fy])
    cd = np.degrees(M @ scale)
    cy = camera.cy
    if rows_reversed:  # v' = -v about the principal point: the second column of CD changes sign
        cd[:, 1] *= -1.0
        cy = camera.height - 1.0 - camera.cy
    w = WCS(naxis=2)
    w.wcs.crpix = [camera.cx + 1.0, cy + 1.0]
    w.wcs.crval = [float(np.degrees(ra)), float(np.degrees(dec))]
    w.wcs.cd = cd
    w.wcs.radesys = "ICRS"
    proj = {"pinhole": "TAN", "equidistant": "ARC", "equisolid": "ZEA"}[camera.model]
    if camera.distorted:
        w.wcs.ctype = [f"RA---{proj}-SIP", f"DEC--{proj}-SIP"]
        a, b, ap, bp = _sip(camera)
        if rows_reversed:  # A(u, -v) and -B(u, -v): the terms in v^q take (-1)^q
            sign = (-1.0) ** np.arange(SIP_ORDER + 1)[None, :]
            a, ap, b, bp = a * sign, ap * sign, -b * sign, -bp * sign
        w.sip = Sip(a, b, ap, bp, w.wcs.crpix)
    else:
        w.wcs.ctype = [f"RA---{proj}", f"DEC--{proj}"]
    w.wcs.set()
    return w


def _sip(camera: Camera):
    """SIP A, B (forward: distorted pixel offsets -> undistorted) and AP, BP (inverse), least squares
    on a grid over the sensor."""
    us = np.linspace(-0.5, camera.width - 0.5, 25) - camera.cx
    vs = np.linspace(-0.5, camera.height - 0.5, 25) - camera.cy
    U, V = np.meshgrid(us, vs)
    ud, vd = U.ravel(), V.ravel()  # distorted offsets (what the image shows)
    xy_d = np.stack([ud / camera.fx, vd / camera.fy], axis=1)
    xy = camera.undistorted_normalised(xy_d)
    uu, vu = xy[:, 0] * camera.fx, xy[:, 1] * camera.fy  # undistorted offsets
    a = _poly_fit(ud, vd, uu - ud)
    b = _poly_fit(ud, vd, vu - vd)
    ap = _poly_fit(uu, vu, ud - uu)
    bp = _poly_fit(uu, vu, vd - vu)
    return a, b, ap, bp


def _poly_fit(u, v, target):
    """SIP coefficient matrix (order SIP_ORDER, terms with 2 <= p + q) fitted to target(u, v)."""
    terms = [(p, q) for p in range(SIP_ORDER + 1) for q in range(SIP_ORDER + 1 - p) if p + q >= 2]
    s = max(np.abs(u).max(), np.abs(v).max(), 1.0)
    A = np.stack([(u / s) ** p * (v / s) ** q for p, q in terms], axis=1)
    coef, *_ = np.linalg.lstsq(A, target, rcond=None)
    m = np.zeros((SIP_ORDER + 1, SIP_ORDER + 1))
    for (p, q), c in zip(terms, coef):
        m[p, q] = c / s ** (p + q)
    return m


def write_wcs(path: str | Path, R: np.ndarray, camera: Camera, *, force: bool = False,
              rows_reversed: bool = False) -> Path:
    """Write the solution's FITS header (a header-only primary HDU) to path, atomically (rows_reversed:
    see `solution_wcs`)."""
    from astropy.io import fits

    from skyview.io.atomic import write_atomic

    p = Path(path)
    hdr = solution_wcs(R, camera, rows_reversed=rows_reversed).to_header(relax=True)
    hdr["IMAGEW"] = (camera.width, "image width, pixels")
    hdr["IMAGEH"] = (camera.height, "image height, pixels")
    hdr["COMMENT"] = "written by skyview: attitude and camera fitted to the identified stars"
    import io

    buf = io.BytesIO()
    fits.PrimaryHDU(header=hdr).writeto(buf)
    write_atomic([(p, buf.getvalue())], force)
    return p
