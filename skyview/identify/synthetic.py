"""Vector-level test frames (no image): the stars a camera sees at an attitude, with noise.

This is the set-up of Cole & Crassidis section IV: the catalog stars in view are rotated into the
camera frame, a Gaussian error of standard deviation sigma is added in the tangent plane and the
vectors are renormalised. A false star (space debris) is placed as in the paper: from the boresight,
along a random direction perpendicular to it, a random length up to half the FOV; it then gets the
same noise as a star. Observed stars are sorted brightest first (by catalog magnitude; a false star
gets a random magnitude in [1, mag_max]).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog
from skyview.identify.base import Observation
from skyview.identify.verify import NEAR_SLACK_RAD, frame_stars


@dataclass
class SyntheticFrame:
    obs: Observation
    truth: np.ndarray  # (N,) true catalog row of each observed star; -1 for a false star
    R: np.ndarray  # the true attitude (v_cam = R v_icrs)

    @property
    def n_true(self) -> int:
        return int(np.sum(self.truth >= 0))

    def all_right(self, matches: dict[int, int]) -> bool:
        """Whether every match (observed index -> catalog row) is the observed star's true row."""
        n = len(matches)
        return bool(np.array_equal(self.truth[np.fromiter(matches.keys(), np.int64, n)],
                                   np.fromiter(matches.values(), np.int64, n)))


def add_noise(v: np.ndarray, sigma_rad: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian tangent-plane error of sigma per axis, renormalised."""
    v = np.atleast_2d(np.asarray(v, dtype=np.float64))
    e = rng.normal(0.0, sigma_rad, size=v.shape)
    e -= np.sum(e * v, axis=1, keepdims=True) * v
    w = v + e
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def false_star_icrs(R: np.ndarray, camera: Camera, rng: np.random.Generator) -> np.ndarray:
    """A false star as in Cole & Crassidis: boresight + (random length <= FOV/2) x random perpendicular."""
    R = np.asarray(R, dtype=np.float64)
    phi = rng.uniform(0.0, 2.0 * np.pi)
    length = rng.uniform(0.0, np.radians(camera.fov_deg) / 2.0)
    v = R[2] + length * (np.cos(phi) * R[0] + np.sin(phi) * R[1])
    return v / np.linalg.norm(v)


def synthetic_frame(catalog: GuideCatalog, camera: Camera, R: np.ndarray, sigma_rad: float,
                    rng: np.random.Generator, false_stars: int = 0) -> SyntheticFrame:
    """The observation of `catalog` by `camera` at attitude R, with noise and optional false stars."""
    R = np.asarray(R, dtype=np.float64)
    # the stars on the sensor, ascending (from the sky index's cone: a sweep makes millions of frames)
    idx = frame_stars(catalog, camera, R)
    v_cam = catalog.xyz[idx] @ R.T
    mags = catalog.mag[idx].astype(np.float64)
    truth = idx.astype(np.int64)
    if false_stars:
        fs = np.array([false_star_icrs(R, camera, rng) for _ in range(false_stars)]) @ R.T
        mag_max = float(catalog.mag.max()) if len(catalog) else 6.0
        v_cam = np.concatenate([v_cam, fs])
        mags = np.concatenate([mags, rng.uniform(1.0, max(mag_max, 1.0), size=false_stars)])
        truth = np.concatenate([truth, -np.ones(false_stars, dtype=np.int64)])
    v_obs = add_noise(v_cam, sigma_rad, rng) if len(v_cam) else np.zeros((0, 3))
    uv, front = camera.project(v_obs) if len(v_obs) else (np.zeros((0, 2)), np.zeros(0, dtype=bool))
    keep = front & camera.in_image(uv) if len(v_obs) else np.zeros(0, dtype=bool)
    order = np.argsort(mags[keep], kind="stable")
    sel = np.flatnonzero(keep)[order]
    obs = Observation(vectors=v_obs[sel], uv=uv[sel], brightness=10.0 ** (-0.4 * mags[sel]), sigma_rad=float(sigma_rad))
    return SyntheticFrame(obs=obs, truth=truth[sel], R=R)


def synthetic_frames(catalog: GuideCatalog, camera: Camera, Rs: np.ndarray, sigma_rad: float,
                     rngs: list[np.random.Generator]) -> list[SyntheticFrame]:
    """`synthetic_frame` for many attitudes at once (a sweep's): Rs (F, 3, 3), frame f's noise drawn from
    rngs[f] as `synthetic_frame` draws it. The same stars, in the same order, with the same noise draws;
    the directions as its to within a few units in the last place (one array operation for all frames
    instead of one per frame)."""
    Rs = np.asarray(Rs, dtype=np.float64).reshape(-1, 3, 3)
    F = len(Rs)
    if len(rngs) != F:
        raise ValueError(f"{F} attitudes need {F} random generators, got {len(rngs)}")
    if F == 0:
        return []
    # the stars frame_stars fetches around each boresight (the sky index's cone of the sensor's
    # half-diagonal and its slack, rows ascending), then the sensor's test for all frames at once
    cone = camera.half_diagonal_rad + 0.0 + 1e-9 + NEAR_SLACK_RAD
    rows = [catalog.sky.cap_cosines(Rs[f, 2], cone)[0] for f in range(F)]
    st = np.concatenate(rows).astype(np.int64)
    fr = np.repeat(np.arange(F), [len(r) for r in rows])
    v = np.einsum("kij,kj->ki", Rs[fr], catalog.xyz[st])
    uv, front = camera.project(v)
    on = front & camera.in_image(uv)
    if camera.distorted and not camera.fisheye:  # (frame_stars: a lens folding stars from beyond the corner)
        on &= v[:, 2] >= np.cos(camera.half_diagonal_rad) - 1e-12
    fr, st, v = fr[on], st[on], v[on]
    # the noise, frame by frame from its own generator (synthetic_frame's draws), then for all at once
    n = np.bincount(fr, minlength=F)
    e = np.concatenate([rngs[f].normal(0.0, sigma_rad, size=(int(n[f]), 3)) for f in range(F)])
    e -= np.sum(e * v, axis=1, keepdims=True) * v
    w = v + e
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    uv, front = camera.project(w)
    keep = front & camera.in_image(uv)
    mags = catalog.mag[st].astype(np.float64)
    sel = np.flatnonzero(keep)
    sel = sel[np.lexsort((mags[sel], fr[sel]))]  # by frame, brightest first (stable: rows ascending on a tie)
    w, uv, mags, truth = w[sel], uv[sel], mags[sel], st[sel]
    brightness = 10.0 ** (-0.4 * mags)
    bounds = np.searchsorted(fr[sel], np.arange(F + 1))
    out = []
    for f in range(F):
        k = slice(bounds[f], bounds[f + 1])
        obs = Observation(vectors=w[k], uv=uv[k], brightness=brightness[k], sigma_rad=float(sigma_rad))
        out.append(SyntheticFrame(obs=obs, truth=truth[k], R=Rs[f]))
    return out
