"""One JSON shape for a solution, wherever it appears.

`skyview solve --json`, each line of `skyview solve-sequence --json`, the API's `Solution.to_json()`
and the viewer's result all start from `solution_dict`: the same keys (SOLUTION_KEYS) with the same
meaning and units, present whether the image solved or not (None where there is no value), so a
consumer reads one shape. Each adds the keys of its own context after them (the image, the frame and
its tracking mode, the identification's statistics).

The keys: status ("solved" / "failed"), solved (bool), reason ("" when solved), notes; the attitude as
R (3 x 3, ICRS -> camera), quaternion ([w, x, y, z], w >= 0), ra_deg / dec_deg / roll_deg, its 1-sigma
sigma_arcsec {boresight, roll} and p_false (the chance that the verified match is an accident); the
method and variant that answered; the camera (its dict), fov_deg, plate_scale_arcsec_per_px,
distortion {k1, k2} and camera_fitted; rows_reversed (the image solved with its rows turned over: a mirror
image of the sky, or a FITS file read the other way up; the attitude, the camera and the matches' u, v are
then those of the image so turned, row v of it being row H - 1 - v of the image as given); mag_limit and epoch of the catalog used; n_centroids,
n_matches and matches ({index, u, v, hip, name, ra_deg, dec_deg, mag, residual_arcsec}); time_ms.
"""

from __future__ import annotations

import math
from typing import Any, Iterable

import numpy as np

from skyview.core.attitude import quat_from_R, radec_roll_from_R
from skyview.core.camera import Camera

RAD_TO_ARCSEC = 180.0 / math.pi * 3600.0
SOLUTION_KEYS = ("status", "solved", "reason", "notes", "R", "quaternion", "ra_deg", "dec_deg", "roll_deg",
                 "sigma_arcsec", "p_false", "method", "variant", "camera", "fov_deg", "plate_scale_arcsec_per_px",
                 "distortion", "camera_fitted", "rows_reversed", "mag_limit", "epoch", "n_centroids", "n_matches",
                 "matches", "time_ms")


def _number(x) -> float | None:
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def solution_dict(*, status: str, reason: str = "", notes: Iterable[str] = (), R: np.ndarray | None = None,
                  sigma_arcsec: tuple[float | None, float | None] | None = None, p_false: float | None = None,
                  method: str | None = None, variant: str | None = None, camera: Camera | None = None,
                  camera_fitted: bool = False, rows_reversed: bool = False, mag_limit: float | None = None,
                  epoch: float | None = None,
                  n_centroids: int = 0, matches: list[dict] | None = None,
                  time_ms: dict[str, float] | None = None) -> dict[str, Any]:
    """The solution's keys (SOLUTION_KEYS), in that order, as plain JSON-able values (non-finite -> None)."""
    solved = status == "solved" and R is not None
    ra = dec = roll = None
    if R is not None:
        a, d, r = radec_roll_from_R(np.asarray(R, dtype=np.float64))
        ra, dec, roll = float(np.degrees(a)), float(np.degrees(d)), float(np.degrees(r))
    matches = list(matches or [])
    b, r = sigma_arcsec if sigma_arcsec is not None else (None, None)
    return {
        "status": status, "solved": solved, "reason": "" if solved else (reason or ""), "notes": list(notes),
        "R": None if R is None else np.asarray(R, dtype=np.float64).tolist(),
        "quaternion": None if R is None else quat_from_R(np.asarray(R, dtype=np.float64)).tolist(),
        "ra_deg": ra, "dec_deg": dec, "roll_deg": roll,
        "sigma_arcsec": {"boresight": _number(b), "roll": _number(r)},
        "p_false": _number(p_false),
        "method": method, "variant": variant,
        "camera": None if camera is None else camera.to_dict(),
        "fov_deg": None if camera is None else camera.fov_deg,
        "plate_scale_arcsec_per_px": None if camera is None else camera.pixel_scale_rad * RAD_TO_ARCSEC,
        "distortion": None if camera is None else {"k1": camera.k1, "k2": camera.k2},
        "camera_fitted": bool(camera_fitted), "rows_reversed": bool(rows_reversed),
        "mag_limit": _number(mag_limit), "epoch": _number(epoch),
        "n_centroids": int(n_centroids), "n_matches": len(matches), "matches": matches,
        "time_ms": {k: round(float(v), 3) for k, v in (time_ms or {}).items() if _number(v) is not None},
    }
