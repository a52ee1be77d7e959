"""Sky coverage outputs: the summary, the table, the Mollweide map (OpenCV), the sphere (.rrd).

`summarize(cfg, res)` bins the sweep's orientations (`skyview.bench.coverage`) into HEALPix pixels (the
sweep's own nside on its HEALPix grid, MAP_NSIDE_SUN for Sun's grid) and gives: the share of
orientations solved / inconclusive / wrong, the share whose field holds at least ENOUGH_STARS stars,
the share of the sphere (equal-area pixels) where every orientation was solved, the worst regions
(the pixels with the lowest solved share), the time per identification and the measured throughput.
`mollweide_png` draws the solved share per pixel on an equal-area Mollweide projection (RA 0 at the
centre, increasing to the left, as the sky is seen), `sphere_mesh` the same colours on a unit sphere
(two triangles per HEALPix pixel), which the .rrd and the viewer's layer
(`skyview.viewer.coverage_layer`) both draw.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np

from skyview.bench.coverage import INCONCLUSIVE, SOLVED, WRONG, CoverageConfig

ENOUGH_STARS = 4  # a field with fewer stars cannot be identified and verified by any method here
MAP_NSIDE_SUN = 16
WORST = 8
SUN_FULL_SWEEP = 12_823_161  # Sun et al. Table 3, third series: RA 0.1 deg x Dec 0.05 deg boresights
_ICRS_TO_GAL = np.array([[-0.0548755604, -0.8734370902, -0.4838350155],
                         [+0.4941094279, -0.4448296300, +0.7469822445],
                         [-0.8676661490, -0.1980763734, +0.4559837762]])


def map_nside(cfg: CoverageConfig) -> int:
    return cfg.nside if cfg.grid == "healpix" else MAP_NSIDE_SUN


def _healpix(nside: int):
    from astropy_healpix import HEALPix

    return HEALPix(nside=nside, order="nested")


def pixel_values(cfg: CoverageConfig, res: dict) -> dict[str, np.ndarray]:
    """Per HEALPix pixel: orientations, solved share, wrong count, mean stars (NaN where none)."""
    import astropy.units as u

    hp = _healpix(map_nside(cfg))
    pix = hp.lonlat_to_healpix(res["ra_deg"] * u.deg, res["dec_deg"] * u.deg)
    n = np.bincount(pix, minlength=hp.npix).astype(np.float64)
    solved = np.bincount(pix, weights=(res["outcome"] == SOLVED), minlength=hp.npix)
    wrong = np.bincount(pix, weights=(res["outcome"] == WRONG), minlength=hp.npix)
    stars = np.bincount(pix, weights=res["stars"], minlength=hp.npix)
    with np.errstate(invalid="ignore", divide="ignore"):
        return {"n": n, "solved": solved / n, "wrong": wrong, "stars": stars / n}


def summarize(cfg: CoverageConfig, res: dict, run: dict | None = None) -> dict:
    n = len(res["outcome"])
    counts = {name: int(np.sum(res["outcome"] == code)) for name, code in
              (("solved", SOLVED), ("inconclusive", INCONCLUSIVE), ("wrong", WRONG))}
    px = pixel_values(cfg, res)
    hp = _healpix(map_nside(cfg))
    have = px["n"] > 0
    lon, lat = hp.healpix_to_lonlat(np.arange(hp.npix))
    ra, dec = np.asarray(lon.deg), np.asarray(lat.deg)
    order = np.lexsort((px["stars"][have], px["solved"][have]))
    worst = []
    for p in np.flatnonzero(have)[order][:WORST]:
        v = np.array([np.cos(np.radians(dec[p])) * np.cos(np.radians(ra[p])),
                      np.cos(np.radians(dec[p])) * np.sin(np.radians(ra[p])), np.sin(np.radians(dec[p]))])
        worst.append({"pixel": int(p), "ra_deg": round(float(ra[p]), 2), "dec_deg": round(float(dec[p]), 2),
                      "gal_lat_deg": round(float(np.degrees(np.arcsin(np.clip(_ICRS_TO_GAL @ v, -1, 1)[2]))), 1),
                      "solved": round(float(px["solved"][p]), 3), "stars_mean": round(float(px["stars"][p]), 2)})
    t = res["time_ms"]
    out = {
        "config": cfg.to_dict(), "description": cfg.describe(), "orientations": n, "counts": counts,
        "coverage_pct": 100.0 * counts["solved"] / n,
        "inconclusive_pct": 100.0 * counts["inconclusive"] / n, "wrong_pct": 100.0 * counts["wrong"] / n,
        "enough_stars_pct": 100.0 * float(np.mean(res["stars"] >= ENOUGH_STARS)), "enough_stars": ENOUGH_STARS,
        "stars": {"median": float(np.median(res["stars"])), "min": int(res["stars"].min()),
                  "max": int(res["stars"].max())},
        "map_nside": map_nside(cfg),
        "sphere_all_solved_pct": 100.0 * float(np.mean(px["solved"][have] == 1.0)),
        "sphere_none_solved_pct": 100.0 * float(np.mean(px["solved"][have] == 0.0)),
        "worst_regions": worst,
        "identify_ms": {"median": float(np.median(t)), "mean": float(np.mean(t)), "p95": float(np.percentile(t, 95))},
    }
    out["run"] = dict(run or {})
    busy = float(res.get("worker_s", 0.0))
    if busy > 0:  # every task's own time on its worker (one core each), frame synthesis included
        per_core = n / busy
        out["run"].update(worker_core_s=busy, orientations_per_s_per_core=per_core,
                          sun_12_8M_core_hours=SUN_FULL_SWEEP / per_core / 3600.0)
    return out


def format_markdown(s: dict) -> str:
    c = s["counts"]
    lines = [f"# Sky coverage: {s['description']}", "",
             "| orientations | solved | inconclusive | wrong | coverage | field with >= "
             f"{s['enough_stars']} stars | sphere where every orientation solved | stars in field median (min-max) "
             "| identify ms median / p95 |",
             "|---|---|---|---|---|---|---|---|---|",
             f"| {s['orientations']} | {c['solved']} | {c['inconclusive']} | {c['wrong']} | {s['coverage_pct']:.2f} % | "
             f"{s['enough_stars_pct']:.2f} % | {s['sphere_all_solved_pct']:.1f} % | {s['stars']['median']:g} "
             f"({s['stars']['min']}-{s['stars']['max']}) | {s['identify_ms']['median']:.2f} / "
             f"{s['identify_ms']['p95']:.2f} |", "",
             f"Worst regions (HEALPix nside {s['map_nside']} pixels, lowest solved share first):", "",
             "| RA (deg) | Dec (deg) | galactic latitude (deg) | solved | stars (mean) |", "|---|---|---|---|---|"]
    for w in s["worst_regions"]:
        lines.append(f"| {w['ra_deg']:.1f} | {w['dec_deg']:.1f} | {w['gal_lat_deg']:.1f} | {w['solved']:.2f} | "
                     f"{w['stars_mean']:.1f} |")
    r = s.get("run") or {}
    if r.get("orientations_per_s_per_core"):
        last = (f"; the last run: {r['tasks_run']} tasks in {r['wall_s']:.1f} s wall on {r['workers']} worker(s) "
                f"({r['scheduler']}, start-up included)" if r.get("wall_s") is not None else "")
        lines += ["", f"Throughput: {r['orientations_per_s_per_core']:.1f} orientations/s per core (every task's own "
                      f"time on its worker, {r['worker_core_s']:.1f} core-s in all){last}. Sun et al.'s 12.8 M "
                      f"orientations would take {r['sun_12_8M_core_hours']:.1f} core-hours."]
    return "\n".join(lines) + "\n"


# ============================================================================ pictures

def colours(solved: np.ndarray) -> np.ndarray:
    """RGB uint8 per value in [0, 1] (viridis: dark = never solved, yellow = always); grey for NaN."""
    v = np.nan_to_num(np.asarray(solved, dtype=np.float64), nan=0.0)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(-1, 1), cv2.COLORMAP_VIRIDIS)[:, 0, ::-1]
    rgb = lut[np.clip(np.rint(v * 255), 0, 255).astype(np.int64)].copy()
    rgb[~np.isfinite(np.asarray(solved, dtype=np.float64))] = (128, 128, 128)
    return rgb


def mollweide_lonlat(width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RA, Dec (degrees) of every pixel of a width x height Mollweide map, and the mask of the ellipse.
    RA 0 at the centre, increasing to the left."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    X = (x + 0.5 - width / 2) / (width / 2) * 2 * np.sqrt(2)
    Y = (height / 2 - y - 0.5) / (height / 2) * np.sqrt(2)
    inside = X ** 2 / 8 + Y ** 2 / 2 <= 1.0
    th = np.arcsin(np.clip(Y / np.sqrt(2), -1, 1))
    lat = np.degrees(np.arcsin(np.clip((2 * th + np.sin(2 * th)) / np.pi, -1, 1)))
    lon = np.degrees(np.pi * X / (2 * np.sqrt(2) * np.maximum(np.cos(th), 1e-12)))
    ra = np.mod(-lon, 360.0)
    return ra, lat, inside


def _mollweide_xy(ra_deg, dec_deg, width: int, height: int) -> np.ndarray:
    lon = np.radians(((-np.asarray(ra_deg) + 180.0) % 360.0) - 180.0)
    lat = np.radians(np.asarray(dec_deg, dtype=np.float64))
    th = lat.copy()
    for _ in range(30):
        th = th - (2 * th + np.sin(2 * th) - np.pi * np.sin(lat)) / np.maximum(2 + 2 * np.cos(2 * th), 1e-9)
    X = 2 * np.sqrt(2) / np.pi * lon * np.cos(th)
    Y = np.sqrt(2) * np.sin(th)
    return np.stack([width / 2 + X / (2 * np.sqrt(2)) * width / 2, height / 2 - Y / np.sqrt(2) * height / 2], -1)


def mollweide_png(cfg: CoverageConfig, res: dict, path: Path, summary: dict, width: int = 900) -> None:
    """The solved share per HEALPix pixel on an equal-area Mollweide map, with a graticule, a title and a
    colour bar; pixels with a wrong identification circled red."""
    import astropy.units as u

    height = width // 2
    px = pixel_values(cfg, res)
    hp = _healpix(map_nside(cfg))
    ra, dec, inside = mollweide_lonlat(width, height)
    pix = hp.lonlat_to_healpix(ra[inside] * u.deg, dec[inside] * u.deg)
    top, bar_h = 34, 46
    img = np.full((height + top + bar_h, width, 3), 255, np.uint8)
    body = img[top:top + height]
    body[inside] = colours(px["solved"][pix])[:, ::-1]
    grey = (235, 235, 235)
    for d in range(-60, 61, 30):
        ras = np.linspace(0, 360, 181)
        pts = _mollweide_xy(ras, np.full_like(ras, d), width, height)
        cv2.polylines(body, [np.rint(pts).astype(np.int32)], False, grey, 1, cv2.LINE_AA)
    for r in range(0, 360, 30):
        ds = np.linspace(-89.9, 89.9, 181)
        pts = _mollweide_xy(np.full_like(ds, r + 1e-6), ds, width, height)
        cv2.polylines(body, [np.rint(pts).astype(np.int32)], False, grey, 1, cv2.LINE_AA)
        x, y = _mollweide_xy(r + 1e-6, 0.0, width, height)
        cv2.putText(body, f"{r}", (int(x) + 2, int(y) - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                    grey, 1, cv2.LINE_AA)
    cv2.ellipse(body, (width // 2, height // 2), (width // 2 - 1, height // 2 - 1), 0, 0, 360, (90, 90, 90), 1,
                cv2.LINE_AA)
    lon, lat = hp.healpix_to_lonlat(np.flatnonzero(px["wrong"] > 0))
    for x, y in _mollweide_xy(np.asarray(lon.deg), np.asarray(lat.deg), width, height):
        cv2.circle(body, (int(x), int(y)), 6, (0, 0, 255), 2, cv2.LINE_AA)
    title = (f"{cfg.method} ({cfg.variant}) {cfg.fov_deg:g} deg, Hp<={cfg.mag_limit:g}: solved "
             f"{summary['coverage_pct']:.1f} % of {summary['orientations']} orientations, wrong "
             f"{summary['counts']['wrong']}")
    cv2.putText(img, title, (8, 23), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (20, 20, 20), 1, cv2.LINE_AA)
    x0, x1, y0 = width // 4, 3 * width // 4, top + height + 10
    ramp = colours(np.linspace(0, 1, x1 - x0))[:, ::-1]
    img[y0:y0 + 12, x0:x1] = ramp[None]
    for v, x in ((0, x0), (0.5, (x0 + x1) // 2), (1, x1)):
        cv2.putText(img, f"{v:g}", (x - 6, y0 + 28), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (20, 20, 20), 1, cv2.LINE_AA)
    cv2.putText(img, "solved share (RA 0 centre, east left)", (x1 + 10, y0 + 11),
                cv2.FONT_HERSHEY_SIMPLEX, 0.38, (20, 20, 20), 1, cv2.LINE_AA)
    ok, buf = cv2.imencode(".png", img)
    tmp = path.with_suffix(".tmp.png")
    tmp.write_bytes(buf.tobytes())
    os.replace(tmp, path)


def sphere_mesh(nside: int, values: np.ndarray, radius: float = 1.0, step: int = 2
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (V, 3) float32, triangles (T, 3) int32 and per-vertex RGB (V, 3) uint8 of the HEALPix
    pixels on a sphere of `radius`, coloured by `values` (one per pixel, in [0, 1]; NaN grey).
    Each pixel is a fan of triangles around its centre over its boundary (step points per side)."""
    hp = _healpix(nside)
    lon, lat = hp.boundaries_lonlat(np.arange(hp.npix), step=step)
    lon, lat = np.asarray(lon.rad), np.asarray(lat.rad)  # (npix, 4 step)
    clon, clat = hp.healpix_to_lonlat(np.arange(hp.npix))
    clon, clat = np.asarray(clon.rad), np.asarray(clat.rad)

    def xyz(lo, la):
        return np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1)

    ring = xyz(lon, lat)  # (npix, m, 3)
    centre = xyz(clon, clat)[:, None, :]
    m = ring.shape[1]
    verts = np.concatenate([centre, ring], axis=1) * radius  # (npix, m + 1, 3)
    base = (np.arange(hp.npix) * (m + 1))[:, None]
    k = np.arange(m)
    tri = np.stack([np.zeros(m, int), 1 + k, 1 + (k + 1) % m], -1)[None] + base[:, None, :]
    rgb = np.repeat(colours(values)[:, None, :], m + 1, axis=1)
    return (verts.reshape(-1, 3).astype(np.float32), tri.reshape(-1, 3).astype(np.int32), rgb.reshape(-1, 3))


def write_rrd(cfg: CoverageConfig, res: dict, path: Path, summary: dict) -> None:
    """The coloured sphere (static), the directions as points (solved share, stars) and the table."""
    import rerun as rr

    px = pixel_values(cfg, res)
    nside = map_nside(cfg)
    v, t, rgb = sphere_mesh(nside, px["solved"])
    tmp = path.with_suffix(".tmp.rrd")
    rec = rr.RecordingStream("skyview", recording_id=f"coverage-{cfg.method}-{cfg.variant}-{cfg.fov_deg:g}",
                             send_properties=False)
    rec.set_log_time_enabled(False)
    rec.save(str(tmp))
    rec.log("sky/coverage", rr.Mesh3D(vertex_positions=v, triangle_indices=t, vertex_colors=rgb), static=True)
    hp = _healpix(nside)
    have = np.flatnonzero(px["n"] > 0)
    lon, lat = hp.healpix_to_lonlat(have)
    lo, la = np.asarray(lon.rad), np.asarray(lat.rad)
    pts = 1.01 * np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1)
    rec.log("sky/directions", rr.Points3D(pts.astype(np.float32), colors=colours(px["solved"][have]), radii=0.004,
                                          labels=[f"solved {px['solved'][p]:.2f}, {px['stars'][p]:.1f} stars"
                                                  for p in have]), static=True)
    rec.log("summary", rr.TextDocument(format_markdown(summary), media_type=rr.MediaType.MARKDOWN), static=True)
    rec.flush()
    rec.disconnect()
    os.replace(tmp, path)


def write_outputs(cfg: CoverageConfig, res: dict, out: Path, run: dict | None = None) -> dict:
    """coverage.json, coverage.md, coverage.png, coverage.rrd in `out`; returns the summary."""
    s = summarize(cfg, res, run)
    s["complete"] = True
    s["files"] = {k: str(out / f"coverage.{k}") for k in ("json", "md", "png", "rrd")}
    mollweide_png(cfg, res, out / "coverage.png", s)
    write_rrd(cfg, res, out / "coverage.rrd", s)
    (out / "coverage.md").write_text(format_markdown(s))
    tmp = out / "coverage.tmp.json"
    tmp.write_text(json.dumps(s, indent=1))
    os.replace(tmp, out / "coverage.json")
    return s


def load_map(out: str | Path) -> tuple[CoverageConfig, dict[str, np.ndarray], dict]:
    """A finished sweep's configuration, per-pixel values (`pixel_values`) and summary."""
    from skyview.bench.coverage import load_config, load_results

    cfg = load_config(out)
    res = load_results(out)
    path = Path(out) / "coverage.json"
    summary = json.loads(path.read_text()) if path.exists() else summarize(cfg, res)
    return cfg, pixel_values(cfg, res), summary
