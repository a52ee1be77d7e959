"""Drawing the sky, the camera, the matches and the current step into a viser scene.

`SkyScene` takes a viser `SceneApi` (a server's or one browser tab's) and draws `Run` objects; it
holds no identification logic and no GUI. The celestial sphere has radius 1 and is seen from its
centre: ICRS unit vectors are the world coordinates, with +z (north) up. Geometry comes from
`skyview.sky_geometry`; a step is drawn from its `skyview.present.StepView` (the drawables the Rerun
recorder renders too): one node per role, `NODES[role]`, in the palette's colours. The identification
(matched stars, their mesh, the green rings) shows only at the last step or when no step is selected:
a step shows what the method knows at that step.
"""

from __future__ import annotations

import math

import numpy as np
import viser.transforms as vtf

from skyview.camera import Camera
from skyview.catalog import GuideCatalog, radec_to_vec, vec_to_radec
from skyview.sky_geometry import (group_segments, magnitude_bins, polylines_as_segments, radec_grid,
                                  sensor_footprint, star_color, star_radius)
from skyview.present import (ARC_POINTS, IMAGE_ROLES, OUTCOME_RGB, PALETTE, SKY_ROLES, SkyLines, SkyPoints, StepView,
                             place_labels)
from skyview.viewer.run import Run

# Proper names of the brightest stars (HIP -> name), for the sky labels.
STAR_NAMES = {
    32349: "Sirius", 30438: "Canopus", 91262: "Vega", 69673: "Arcturus", 71683: "Rigil Kentaurus",
    24436: "Rigel", 24608: "Capella", 7588: "Achernar", 37279: "Procyon", 27989: "Betelgeuse",
    68702: "Hadar", 60718: "Acrux", 97649: "Altair", 65474: "Spica", 80763: "Antares", 21421: "Aldebaran",
    62434: "Mimosa", 113368: "Fomalhaut", 37826: "Pollux", 102098: "Deneb", 49669: "Regulus",
    33579: "Adhara", 85927: "Shaula", 25336: "Bellatrix", 36850: "Castor", 25428: "Elnath",
    26311: "Alnilam", 61084: "Gacrux", 45238: "Miaplacidus", 26727: "Alnitak", 109268: "Alnair",
    11767: "Polaris", 25930: "Mintaka", 27366: "Saiph", 54061: "Dubhe", 53910: "Merak", 62956: "Alioth",
    65378: "Mizar", 67301: "Alkaid", 3179: "Schedar", 746: "Caph", 677: "Alpheratz", 15863: "Mirfak",
    14576: "Algol", 9884: "Hamal",
}
NAME_MAG_LIMIT = 1.7  # stars at least this bright get a name label (named ones down to mag 2.4 too)
NAME_CHAR_PX, NAME_HEIGHT_PX = 7.5, 16.0  # a name label's character width and height on screen
VIEW_HEIGHT_PX = 860.0  # the 3-D view's height the label sizes assume
REFERENCE_TAN = math.tan(math.radians(30.0))  # the view at zoom 1 (as the session's)

# Colours (RGB).
GRID_RGB = PALETTE["grid"]
GRID_MAIN_RGB = PALETTE["grid_main"]
FINE_GRID_RGB = (40, 56, 84)
EST_RGB = PALETTE["estimated"]
TRUE_RGB = PALETTE["true"]
MATCH_RGB = PALETTE["identified"]
TRACK_RGB = (60, 120, 150)  # the footprints of a sequence's frames
BACKGROUND_TOP = (10, 13, 30)
BACKGROUND_BOTTOM = (3, 4, 10)

IMAGE_DEPTH = 1.003  # the sensor image sits just beyond the sphere: catalog stars draw in front of it
RING_PX = 9.0  # centroid ring radius in sensor pixels (for a 1024-pixel sensor; scaled with size)
STAR_SIZE = 0.75  # point size = STAR_SIZE * sky_geometry.star_radius(mag) * zoom factor

# Node names, for tests and for anyone scripting the viewer.
NODES = {
    "stars": "/sky/stars",  # one cloud per magnitude bin: /sky/stars/bin<k>
    "grid": "/sky/grid/lines",
    "grid_main": "/sky/grid/main",
    "grid_labels": "/sky/grid/labels",
    "fine_grid": "/sky/fine_grid/lines",
    "fine_labels": "/sky/fine_grid/labels",
    "names": "/sky/names",
    "pick": "/sky/pick",
    "camera": "/camera/est",
    "frustum": "/camera/est/frustum",
    "centroids": "/camera/est/centroids",
    "numbers": "/camera/est/numbers",
    "observed": "/camera/est/observed",  # the stars the step measured (rings in the image)
    "pattern": "/camera/est/pattern",  # ... and their pattern
    "known": "/camera/est/known",  # stars measured by earlier steps (faded rings)
    "footprint": "/footprint/est",
    "true_camera": "/camera/true",
    "true_frustum": "/camera/true/frustum",
    "true_footprint": "/footprint/true",
    "candidates": "/steps/candidates",  # the step roles of skyview.present, one node each
    "candidate_stars": "/steps/candidate_stars",
    "points": "/steps/points",
    "attitudes": "/steps/attitudes",
    "outline": "/steps/outline",
    "matches": "/matches/triangles",
    "match_stars": "/matches/stars",
    "match_labels": "/matches/labels",
    "track": "/sequence/track",  # every frame's true footprint, when a sequence is shown
    "track_labels": "/sequence/labels",  # frame numbers at the frames' boresights
}


def _f32(a) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float32))


def pose_wxyz(R: np.ndarray) -> np.ndarray:
    """Camera -> world rotation of skyview's R (v_cam = R v_icrs) as viser's wxyz."""
    return vtf.SO3.from_matrix(np.asarray(R, dtype=np.float64).T).wxyz


def frustum_scale(camera: Camera, depth: float) -> float:
    """viser normalises its frustum's volume: the `scale` that puts the far plane at `depth`."""
    ty = camera.height / (2.0 * camera.fy)
    tx = camera.width / (2.0 * camera.fx)
    return float(depth * np.cbrt(tx * ty / 3.0))


def ray_to_sphere(origin, direction) -> np.ndarray | None:
    """Where a view ray leaves the unit sphere (the far root: the sky seen from inside)."""
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    b = o @ d
    c = o @ o - 1.0
    disc = b * b - c
    if disc < 0:
        return None
    t = -b + math.sqrt(disc)
    if t <= 0:
        return None
    p = o + t * d
    return p / np.linalg.norm(p)


def nice_step(fov_deg: float) -> float:
    """Fine-grid spacing: about a third of the field, from a round list."""
    for s in (0.25, 0.5, 1.0, 2.0, 5.0, 10.0):
        if s >= fov_deg / 4.0:
            return s
    return 15.0


def local_grid(b: np.ndarray, radius_rad: float, step_deg: float, n_per_line: int = 80):
    """RA/Dec lines every `step_deg` within `radius_rad` of `b`: segments and label anchors.

    Returns (segments (S, 2, 3), labels [(text, xyz)]): meridians labelled along the grid parallel
    nearest to `b`, parallels along the nearest meridian.
    """
    ra0, dec0 = (math.degrees(x) for x in vec_to_radec(np.asarray(b, dtype=np.float64)))
    r = math.degrees(radius_rad)
    dec_lo, dec_hi = max(-90.0, dec0 - r), min(90.0, dec0 + r)
    cos_edge = math.cos(math.radians(max(abs(dec_lo), abs(dec_hi))))
    if dec_hi >= 89.999 or dec_lo <= -89.999 or cos_edge < 1e-3 or r / cos_edge >= 180:
        ra_lo, ra_hi = 0.0, 360.0
    else:
        half = r / cos_edge
        ra_lo, ra_hi = ra0 - half, ra0 + half
    lines = []
    ras = np.arange(math.ceil(ra_lo / step_deg) * step_deg, ra_hi + 1e-9, step_deg)
    ras = ras[ras < ra_lo + 360.0 - 1e-9] if ra_hi - ra_lo >= 360.0 else ras
    decs = np.arange(math.ceil(dec_lo / step_deg) * step_deg, dec_hi + 1e-9, step_deg)
    decs = decs[(decs > -90.0) & (decs < 90.0)]
    dd = np.radians(np.linspace(dec_lo, dec_hi, n_per_line))
    for ra in ras:
        lines.append(radec_to_vec(np.full_like(dd, math.radians(ra)), dd))
    rr = np.radians(np.linspace(ra_lo, ra_hi, 2 * n_per_line))
    for dec in decs:
        lines.append(radec_to_vec(rr, np.full_like(rr, math.radians(dec))))
    segs = polylines_as_segments(lines)
    if len(segs):
        mid = segs.mean(axis=1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        segs = segs[mid @ b >= math.cos(radius_rad)]
    labels = []
    if len(decs):
        d_near = float(decs[np.argmin(np.abs(decs - dec0))])
        for ra in ras:
            p = radec_to_vec(math.radians(ra), math.radians(d_near))
            if p @ b >= math.cos(radius_rad * 0.9):
                labels.append((f"{ra % 360:g}°", p))
    if len(ras):
        diff = (ras - ra0 + 180.0) % 360.0 - 180.0
        ra_near = float(ras[np.argmin(np.abs(diff))])
        for dec in decs:
            p = radec_to_vec(math.radians(ra_near), math.radians(dec))
            if p @ b >= math.cos(radius_rad * 0.9):
                labels.append((f"{dec:+g}°", p))
    return segs, labels


def ring_segments(xy: np.ndarray, radius: float, depth: float, n: int = 14) -> np.ndarray:
    """Circles (as segments) around points of the plane z = depth in the camera frame."""
    if len(xy) == 0:
        return np.zeros((0, 2, 3), dtype=np.float32)
    t = np.linspace(0.0, 2.0 * np.pi, n + 1)
    c = np.stack([np.cos(t), np.sin(t)], axis=1) * radius  # (n+1, 2)
    pts = xy[:, None, :] + c[None, :, :]  # (N, n+1, 2)
    p3 = np.concatenate([pts, np.full(pts.shape[:2] + (1,), depth)], axis=2)
    return np.stack([p3[:, :-1], p3[:, 1:]], axis=2).reshape(-1, 2, 3)


class SkyScene:
    """The 3-D scene of one viewer session."""

    def __init__(self, scene):
        self.scene = scene
        self.h: dict = {}
        self.zoom = 1.0
        self._sized: dict[str, list] = {"stars": [], "run": [], "step": []}  # group -> [(handle, base size)]
        self._catalog_key = None
        self._grid_key = None
        self.bytes_catalog = 0
        self.visible = {"grid": True, "names": True, "image": True, "true": True, "matches": True, "track": True,
                        "numbers": True, "hips": False, "stars": True, "candidates": True}
        self._run: Run | None = None
        self._image_plane_xy = np.zeros((0, 2))
        self._ring = 0.0
        self._tex: np.ndarray | None = None
        self.detail = True  # centroid numbers and fine-grid labels: only when the field fills the view
        self.final = True  # the identification is on screen (last step, or no step selected)
        self._names: tuple | None = None  # star names: (positions, magnitudes, lengths) for their placement
        self._name_keep: np.ndarray | None = None
        self._ring_colors: np.ndarray | None = None

    # ------------------------------------------------------------------ sky
    def setup(self) -> None:
        """Background, coarse grid and its labels (independent of the catalog)."""
        s = self.scene
        s.set_up_direction("+z")
        g = np.linspace(0.0, 1.0, 64)[:, None, None]
        bg = ((1 - g) * np.array(BACKGROUND_TOP) + g * np.array(BACKGROUND_BOTTOM)) * np.ones((1, 4, 1))
        s.set_background_image(bg.astype(np.uint8), format="png")
        # seen from the centre a chord is a great-circle arc: meridians need few points, parallels some
        lines = radec_grid(30.0, 15.0, n_points=37)
        ra = np.radians(np.linspace(0.0, 360.0, 73))
        dec = np.radians(np.linspace(-90.0, 90.0, 13))
        main = [radec_to_vec(ra, np.zeros_like(ra)), radec_to_vec(np.zeros_like(dec), dec)]  # equator, RA 0h
        self.h["grid"] = s.add_line_segments(NODES["grid"], _f32(polylines_as_segments(lines)), GRID_RGB,
                                             thickness=1.0, thickness_units="screen")
        self.h["grid_main"] = s.add_line_segments(NODES["grid_main"], _f32(polylines_as_segments(main)),
                                                  GRID_MAIN_RGB, thickness=1.6, thickness_units="screen")
        labels = []
        for hour in range(0, 24, 2):
            labels.append((f"{hour}h", radec_to_vec(math.radians(15.0 * hour), math.radians(1.0))))
        for ra_h in (0, 12):
            for dec in (-60, -30, 30, 60):
                labels.append((f"{dec:+d}°", radec_to_vec(math.radians(15.0 * ra_h + 1.0), math.radians(dec))))
        labels += [("N pole", np.array([0.0, 0.0, 1.0])), ("S pole", np.array([0.0, 0.0, -1.0]))]
        self.h["grid_labels"] = [
            s.add_label(f"{NODES['grid_labels']}/{k}", text, position=_f32(p), font_screen_scale=0.8,
                        anchor="bottom-left")
            for k, (text, p) in enumerate(labels)]

    def draw_catalog(self, catalog: GuideCatalog) -> None:
        """The guide catalog on the sphere (one cloud per magnitude bin) and the bright stars' names."""
        key = (catalog.fingerprint, len(catalog))
        if key == self._catalog_key:
            return
        self._catalog_key = key
        s = self.scene
        self._sized["stars"] = []
        for hd in self.h.pop("stars", []):
            hd.remove()
        colors = star_color(catalog.mag, catalog.bv)
        self.h["stars"] = []
        nbytes = 0
        for k, idx in enumerate(magnitude_bins(catalog.mag)):
            if len(idx) == 0:
                continue
            base = float(STAR_SIZE * star_radius(np.mean(catalog.mag[idx])))
            pts, col = _f32(catalog.xyz[idx]), np.ascontiguousarray(colors[idx])
            nbytes += pts.nbytes + col.nbytes
            hd = s.add_point_cloud(f"{NODES['stars']}/bin{k}", pts, col, point_size=base * self.zoom,
                                   point_shape="circle", precision="float32", visible=self.visible["stars"])
            self.h["stars"].append(hd)
            self._sized["stars"].append((hd, base))
        self.bytes_catalog = nbytes
        for hd in self.h.pop("names", []):
            hd.remove()
        names = []
        rows = np.flatnonzero((catalog.mag <= NAME_MAG_LIMIT) | np.isin(catalog.hip, list(STAR_NAMES)))
        texts = []
        for i in rows:
            hip = int(catalog.hip[i])
            texts.append(f"{STAR_NAMES.get(hip, f'HIP {hip}')} {float(catalog.mag[i]):.1f}")
            names.append(s.add_label(f"{NODES['names']}/{hip}", texts[-1], position=_f32(catalog.xyz[i] * 1.0),
                                     font_screen_scale=0.85, anchor="top-left", visible=False))
        self.h["names"] = names
        ra, dec = vec_to_radec(catalog.xyz[rows])
        self._names = (np.stack([np.asarray(ra) * np.cos(dec), np.asarray(dec)], axis=1), catalog.mag[rows],
                       np.array([len(t) for t in texts], dtype=np.float64))
        self._place_names()

    def _place_names(self) -> None:
        """Show the star names that do not overlap a brighter one's at this zoom (`present.place_labels`)."""
        hds = self.h.get("names", [])
        if not hds or self._names is None:
            return
        xy, mag, n_chars = self._names
        span = REFERENCE_TAN * self.zoom ** (1.0 / 0.85)  # half-height of the view at the sphere (Session zoom)
        per_px = 2.0 * span / VIEW_HEIGHT_PX  # sphere units per screen pixel
        sizes = np.stack([n_chars * NAME_CHAR_PX * per_px, np.full_like(n_chars, NAME_HEIGHT_PX * per_px)], axis=1)
        keep = place_labels(xy, mag, sizes, gap=0.0)
        for hd, k in zip(hds, keep):
            hd.visible = bool(k) and self.visible["names"]
        self._name_keep = keep

    def draw_fine_grid(self, b: np.ndarray, fov_deg: float, radius_rad: float) -> None:
        """A finer RA/Dec grid around the boresight, labelled in degrees."""
        step = nice_step(fov_deg)
        key = (tuple(np.round(b, 4)), step)
        if key == self._grid_key:
            return
        self._grid_key = key
        segs, labels = local_grid(b, radius_rad, step)
        s = self.scene
        for hd in self.h.pop("fine_labels", []):
            hd.remove()
        if "fine_grid" in self.h:
            self.h.pop("fine_grid").remove()
        if len(segs):
            self.h["fine_grid"] = s.add_line_segments(NODES["fine_grid"], _f32(segs), FINE_GRID_RGB, thickness=1.0,
                                                      thickness_units="screen", visible=self.visible["grid"])
        self.h["fine_labels"] = [
            s.add_label(f"{NODES['fine_labels']}/{k}", text, position=_f32(p), font_screen_scale=0.7,
                        anchor="bottom-left", visible=self.visible["grid"] and self.detail)
            for k, (text, p) in enumerate(labels[:16])]

    # ------------------------------------------------------------------ camera
    def draw_run(self, run: Run, tex: np.ndarray | None) -> None:
        """Camera(s), footprints, centroids and matches of a run; the step layer is reset."""
        s = self.scene
        cam = run.source.camera
        R = run.R_shown
        for hd in self.h.pop("match_labels", []) + self.h.pop("numbers", []):
            hd.remove()
        for key in ("frustum", "centroids", "observed", "pattern", "true_frustum",  # children first
                    "camera", "true_camera", "footprint", "true_footprint", "matches", "match_stars"):
            if key in self.h:
                self.h.pop(key).remove()
        self._tex = tex
        self._sized["run"] = []
        if R is None:  # an image that did not solve: no pose to draw it at
            for hd in self.h.pop("fine_labels", []):
                hd.remove()
            if "fine_grid" in self.h:
                self.h.pop("fine_grid").remove()
            self._grid_key = None
            self._run = None
            self.show_step(run, None)
            return
        catalog = run.catalog
        self._run = run
        self.draw_fine_grid(R[2], cam.fov_deg, 1.8 * cam.half_diagonal_rad)
        depth = IMAGE_DEPTH
        self.h["camera"] = s.add_frame(NODES["camera"], wxyz=pose_wxyz(R), position=(0.0, 0.0, 0.0), show_axes=False)
        self.h["frustum"] = s.add_camera_frustum(
            NODES["frustum"], fov=math.radians(cam.fov_v_deg), aspect=cam.width / cam.height,
            scale=frustum_scale(cam, depth), color=EST_RGB if run.result.R is not None else TRUE_RGB,
            thickness=1.5, thickness_units="screen", image=tex if self.visible["image"] else None,
            format="jpeg", jpeg_quality=85)
        self.h["footprint"] = s.add_line_segments(
            NODES["footprint"], _f32(polylines_as_segments([sensor_footprint(cam, R)])),
            EST_RGB if run.result.R is not None else TRUE_RGB, thickness=2.0, thickness_units="screen")
        # centroids: rings on the image plane, coloured by outcome, numbered by brightness
        uv = run.result.centroids.uv
        xy = (uv - np.array([cam.cx, cam.cy])) / np.array([cam.fx, cam.fy]) * depth
        self._image_plane_xy = xy
        ring = RING_PX * max(cam.width, cam.height) / 1024.0 / cam.fx * depth
        self._ring = ring
        segs, cols = [], []
        for i, o in enumerate(run.outcomes):
            rs = ring_segments(xy[i:i + 1], ring, depth * 0.9995)
            segs.append(rs)
            cols.append(np.broadcast_to(np.array(OUTCOME_RGB[o], np.uint8), rs.shape))
        self._ring_colors = None
        if segs:
            self._ring_colors = np.ascontiguousarray(np.concatenate(cols))  # at the end: coloured by outcome
            self.h["centroids"] = s.add_line_segments(NODES["centroids"], _f32(np.concatenate(segs)),
                                                      self._ring_colors, thickness=1.5, thickness_units="screen")
        self.h["numbers"] = [
            s.add_label(f"{NODES['numbers']}/{i}", str(i),
                        position=_f32([xy[i, 0] + ring * 0.8, xy[i, 1] - ring * 0.8, depth * 0.999]),
                        font_screen_scale=0.7, anchor="bottom-left",
                        visible=self.visible["numbers"] and self.detail)
            for i in range(min(len(xy), 40))]
        if run.R_true is not None and run.result.R is not None:
            self.h["true_camera"] = s.add_frame(NODES["true_camera"], wxyz=pose_wxyz(run.R_true),
                                                position=(0.0, 0.0, 0.0), show_axes=False,
                                                visible=self.visible["true"])
            self.h["true_frustum"] = s.add_camera_frustum(
                NODES["true_frustum"], fov=math.radians(cam.fov_v_deg), aspect=cam.width / cam.height,
                scale=frustum_scale(cam, depth * 1.001), color=TRUE_RGB, thickness=1.0, thickness_units="screen")
            self.h["true_footprint"] = s.add_line_segments(
                NODES["true_footprint"], _f32(polylines_as_segments([sensor_footprint(cam, run.R_true)])),
                TRUE_RGB, thickness=1.2, thickness_units="screen", visible=self.visible["true"])
        # matches: triangles between the matched catalog stars, the stars themselves and their HIP ids
        if run.matches:
            rows = np.array(sorted(set(run.matches.values())), dtype=np.int64)
            segs = group_segments(catalog.xyz, run.match_groups, ARC_POINTS)
            if len(segs):
                self.h["matches"] = s.add_line_segments(NODES["matches"], _f32(segs), MATCH_RGB, thickness=2.0,
                                                        thickness_units="screen", visible=self.visible["matches"])
            base = float(STAR_SIZE * star_radius(4.0))
            self.h["match_stars"] = s.add_point_cloud(
                NODES["match_stars"], _f32(catalog.xyz[rows]), MATCH_RGB, point_size=base * self.zoom,
                point_shape="circle", precision="float32", visible=self.visible["matches"])
            self._sized["run"].append((self.h["match_stars"], base))
            self._draw_match_labels()
        self._ensure_step_nodes()
        self.show_step(run, None)

    def _draw_match_labels(self) -> None:
        """HIP id and magnitude at each matched star (the 25 brightest), when switched on."""
        for hd in self.h.pop("match_labels", []):
            hd.remove()
        run = self._run
        if run is None or not run.matches or not (self.visible["hips"] and self.visible["matches"]):
            return
        catalog = run.catalog
        rows = np.array(sorted(set(run.matches.values())), dtype=np.int64)
        self.h["match_labels"] = [
            self.scene.add_label(f"{NODES['match_labels']}/{int(catalog.hip[r])}",
                                 f"HIP {int(catalog.hip[r])} {float(catalog.mag[r]):.1f}",
                                 position=_f32(catalog.xyz[r]), font_screen_scale=0.7, anchor="top-right")
            for r in rows[np.argsort(catalog.mag[rows])][:25]]

    # ------------------------------------------------------------------ steps
    def _ensure_step_nodes(self) -> None:
        """One node per step role of skyview.present (hidden until a step draws it)."""
        s = self.scene
        empty_seg = np.zeros((1, 2, 3), dtype=np.float32)
        if "candidates" not in self.h:
            self._sized["step"] = []
            for role in SKY_ROLES:
                if role in ("candidate_stars", "points"):
                    base = float(STAR_SIZE * star_radius(3.0 if role == "candidate_stars" else 0.5))
                    self.h[role] = s.add_point_cloud(
                        NODES[role], np.zeros((1, 3), np.float32), np.array([PALETTE["candidates"]], np.uint8),
                        point_size=base * self.zoom, point_shape="circle" if role == "candidate_stars" else "diamond",
                        precision="float32", visible=False)
                    self._sized["step"].append((self.h[role], base))
                else:
                    self.h[role] = s.add_line_segments(NODES[role], empty_seg, PALETTE[role], visible=False,
                                                       thickness=2.5 if role == "outline" else 1.4,
                                                       thickness_units="screen")
        if "camera" in self.h and "observed" not in self.h:  # children of the camera frame
            for role in IMAGE_ROLES:
                self.h[role] = s.add_line_segments(NODES[role], empty_seg, PALETTE["observed"], visible=False,
                                                   thickness=2.0 if role == "pattern" else 2.5,
                                                   thickness_units="screen")

    def show_step(self, run: Run | None, k: int | None) -> StepView | None:
        """Draw step k (None: no step, the final state): its drawables, one node per role; the
        identification only when the step is the last one or no step is selected."""
        self._ensure_step_nodes()
        d = run.drawables[k] if (run is not None and k is not None and 0 <= k < len(run.drawables)) else None
        on = self.visible["candidates"] and d is not None
        for role in SKY_ROLES:
            hd = self.h[role]
            dr = d.drawables.get(role) if on else None
            if isinstance(dr, SkyLines) and len(dr.segments):
                hd.points = _f32(dr.segments)
                hd.colors = np.broadcast_to(np.array(dr.color, np.uint8), dr.segments.shape).copy()
                hd.visible = True
            elif isinstance(dr, SkyPoints) and len(dr.xyz):
                hd.points = _f32(dr.xyz)
                hd.colors = np.ascontiguousarray(dr.colors.astype(np.uint8))
                hd.visible = True
            else:
                hd.visible = False
        if "observed" in self.h:
            xy = self._image_plane_xy
            p3 = np.concatenate([xy, np.full((len(xy), 1), IMAGE_DEPTH * 0.999)], axis=1)
            for role in IMAGE_ROLES:
                hd = self.h[role]
                dr = d.drawables.get(role) if d is not None else None
                seg = np.zeros((0, 2, 3))
                if dr is not None and role == "pattern":
                    e = dr.edges[(dr.edges < len(xy)).all(axis=1)] if len(dr.edges) else dr.edges
                    if len(e):
                        seg = np.stack([p3[e[:, 0]], p3[e[:, 1]]], axis=1)
                elif dr is not None:
                    sel = dr.observed[dr.observed < len(xy)]
                    if len(sel):
                        seg = ring_segments(xy[sel], self._ring * (1.7 if role == "observed" else 1.35),
                                            IMAGE_DEPTH * 0.999)
                if len(seg):
                    hd.points = _f32(seg)
                    hd.colors = np.broadcast_to(np.array(dr.color, np.uint8), seg.shape).copy()
                    hd.visible = True
                else:
                    hd.visible = False
        self._show_identification(d is None or d.final)
        return d

    def _show_identification(self, final: bool) -> None:
        """The identification (matched stars and mesh, centroid rings by outcome) only once it is made."""
        self.final = final
        for key in ("matches", "match_stars"):
            if key in self.h:
                self.h[key].visible = final and self.visible["matches"]
        for hd in self.h.get("match_labels", []):
            hd.visible = final
        rings = self.h.get("centroids")
        if rings is not None and self._ring_colors is not None:
            cols = self._ring_colors if final else np.broadcast_to(
                np.array(OUTCOME_RGB["unidentified"], np.uint8), self._ring_colors.shape).copy()
            rings.colors = cols

    # ------------------------------------------------------------------ a sequence
    def draw_track(self, camera: Camera | None, attitudes: list[np.ndarray] | None) -> None:
        """The footprints of a sequence's frames (at their true attitudes), numbered; None removes them."""
        for hd in self.h.pop("track_labels", []):
            hd.remove()
        if "track" in self.h:
            self.h.pop("track").remove()
        if camera is None or not attitudes:
            return
        segs = polylines_as_segments([sensor_footprint(camera, R) for R in attitudes])
        self.h["track"] = self.scene.add_line_segments(NODES["track"], _f32(segs), TRACK_RGB, thickness=1.0,
                                                       thickness_units="screen", visible=self.visible["track"])
        top = np.array([0.0, -0.9 * camera.height / (2.0 * camera.fy), 1.0])  # just inside the top edge
        top /= np.linalg.norm(top)
        self.h["track_labels"] = [
            self.scene.add_label(f"{NODES['track_labels']}/{k}", f"frame {k}", position=_f32(R.T @ top),
                                 font_screen_scale=0.75, anchor="top-center", visible=self.visible["track"])
            for k, R in enumerate(attitudes)]

    # ------------------------------------------------------------------ interaction
    def set_zoom(self, zoom: float) -> None:
        """Scale every star-like point cloud (stars look alike at every zoom)."""
        self.zoom = float(zoom)
        for group in self._sized.values():
            for hd, base in group:
                hd.point_size = base * self.zoom
        self._place_names()

    def set_detail(self, on: bool) -> None:
        """Show the field's small labels (centroid numbers, fine grid) only when zoomed in on it."""
        if on == self.detail:
            return
        self.detail = on
        for hd in self.h.get("numbers", []):
            hd.visible = on and self.visible["numbers"]
        for hd in self.h.get("fine_labels", []):
            hd.visible = on and self.visible["grid"]

    def set_visible(self, what: str, on: bool) -> None:
        self.visible[what] = bool(on)
        if what == "image" and "frustum" in self.h:
            self.h["frustum"].image = self._tex if on else None
        if what == "candidates":
            for key in SKY_ROLES:
                if key in self.h and not on:
                    self.h[key].visible = False
        if what in ("hips", "matches"):
            self._draw_match_labels()
        if what == "names":  # the names that do not collide at this zoom
            self._place_names()
        groups = {
            "grid": ["grid", "grid_main", "grid_labels", "fine_grid", "fine_labels"],
            "stars": ["stars"],
            "true": ["true_camera", "true_footprint"],
            "matches": ["matches", "match_stars"] if self.final else [],
            "numbers": ["numbers"],
            "track": ["track", "track_labels"],
        }
        for key in groups.get(what, []):
            hd = self.h.get(key)
            for one in (hd if isinstance(hd, list) else [hd] if hd is not None else []):
                one.visible = on and (self.detail or key not in ("numbers", "fine_labels"))

    def show_pick(self, catalog: GuideCatalog, row: int | None, text: str = "") -> None:
        if "pick" in self.h:
            self.h.pop("pick").remove()
        if row is not None:
            self.h["pick"] = self.scene.add_label(NODES["pick"], text, position=_f32(catalog.xyz[row]),
                                                  font_screen_scale=0.95, anchor="bottom-left")


def nearest_star(catalog: GuideCatalog, direction: np.ndarray, max_angle_rad: float) -> int | None:
    """Row of the catalog star nearest to a direction, if within max_angle_rad."""
    d, i = catalog.tree.query(np.asarray(direction, dtype=np.float64))
    if not np.isfinite(d) or 2.0 * math.asin(min(1.0, d / 2.0)) > max_angle_rad:
        return None
    return int(i)
