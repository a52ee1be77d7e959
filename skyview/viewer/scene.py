"""Drawing the sky, the camera, the matches and the current step into a viser scene.

`SkyScene` takes a viser `SceneApi` (a server's or one browser tab's) and draws `Run` objects; it
holds no identification logic and no GUI. The celestial sphere has radius 1 and is seen from its
centre: ICRS unit vectors are the world coordinates, with +z (north) up. Geometry comes from
`skyview.core.sky_geometry`; a step is drawn from its `skyview.present.drawables.StepView` (the drawables the Rerun
recorder renders too): one node per role, `NODES[role]`, in the palette's colours. The identification
(matched stars, their mesh, the green rings) shows only at the last step or when no step is selected:
a step shows what the method knows at that step.
"""

from __future__ import annotations

import math

import numpy as np

from skyview.core.camera import Camera
from skyview.core.catalog import GuideCatalog, designation, radec_to_vec, vec_to_radec
from skyview.core.sky_geometry import (
    group_segments,
    magnitude_bins,
    polylines_as_segments,
    radec_grid,
    sensor_footprint,
    star_color,
    star_radius,
)
from skyview.present.constellations import constellations
from skyview.present.drawables import (
    ARC_POINTS,
    IMAGE_ROLES,
    OUTCOME_RGB,
    PALETTE,
    SKY_ROLES,
    SkyLines,
    SkyPoints,
    StepView,
    place_labels,
)
from skyview.viewer.geometry import (
    STAR_NAMES,
    fisheye_photo_glb,
    frustum_scale,
    image_plane_xy,
    local_grid,
    nice_step,
    pose_wxyz,
    ring_segments,
    sky_grid_labels,
    sky_ring_segments,
)
from skyview.viewer.run import Run

NAME_MAG_LIMIT = 1.7  # stars at least this bright get a name label (named ones down to mag 2.4 too)
NAME_CHAR_PX, NAME_PAD_PX, NAME_HEIGHT_PX = 4.8, 4.0, 13.0  # a name label on screen (scale 0.85): px/char, pad, height
VIEW_HEIGHT_PX = 860.0  # the 3-D view's height the label sizes assume
REFERENCE_TAN = math.tan(math.radians(30.0))  # the view at zoom 1 (as the session's)

# Colours (RGB).
GRID_RGB = PALETTE["grid"]
GRID_MAIN_RGB = PALETTE["grid_main"]
FINE_GRID_RGB = (40, 56, 84)
EST_RGB = PALETTE["estimated"]
TRUE_RGB = PALETTE["true"]
MATCH_RGB = PALETTE["identified"]
FIGURE_RGB = PALETTE["constellation"]
TRACK_RGB = (60, 120, 150)  # the footprints of a sequence's frames
BACKGROUND_TOP = (10, 13, 30)
BACKGROUND_BOTTOM = (3, 4, 10)

FIGURE_DEPTH = 0.999  # constellation figures sit just inside the sphere
IMAGE_DEPTH = 1.003  # the sensor image sits just beyond the sphere: catalog stars draw in front of it
RING_PX = 9.0  # centroid ring radius in sensor pixels (for a 1024-pixel sensor; scaled with size)
STAR_SIZE = 0.75  # point size = STAR_SIZE * sky_geometry.star_radius(mag) * zoom factor

# Node names, for tests and for anyone scripting the viewer.
NODES = {
    "stars": "/sky/stars",  # one cloud per magnitude bin: /sky/stars/bin<k>
    "grid": "/sky/grid/lines",
    "grid_main": "/sky/grid/main",
    "grid_labels": "/sky/grid/labels",
    "figures": "/sky/constellations/figures",  # the 88 constellations' stick figures
    "figure_names": "/sky/constellations/names",
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
    "candidates": "/steps/candidates",  # the step roles of skyview.present.drawables, one node each
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


def _name_plane(xyz: np.ndarray) -> np.ndarray:
    """Where names are placed against each other: (RA cos Dec, Dec), radians."""
    ra, dec = vec_to_radec(xyz)
    return np.stack([np.asarray(ra) * np.cos(dec), np.asarray(dec)], axis=1)


def _f32(a) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float32))


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
        self.visible = {"grid": True, "constellations": True, "names": True, "image": True, "true": True,
                        "matches": True, "track": True, "numbers": True, "hips": False, "stars": True,
                        "candidates": True}
        self._run: Run | None = None
        self._image_plane_xy, self._ring = np.zeros((0, 2)), 0.0  # centroids on the image plane, ring radius
        # a fisheye's photograph: its centroids' directions in the camera frame (None: a pinhole's, on the plane)
        self._mark_dirs: np.ndarray | None = None
        self._tex: np.ndarray | None = None
        self.detail = True  # centroid numbers and fine-grid labels: only when the field fills the view
        self.final = True  # the identification is on screen (last step, or no step selected)
        self._names: tuple | None = None  # star names: (positions, magnitudes, lengths) for their placement
        self._figure_names: tuple | None = None  # the constellations' names: (positions, lengths)
        self._name_keep, self._name_xyz = None, np.zeros((0, 3))  # the names shown, where they are
        self._grid_labels: list[tuple[str, np.ndarray]] = []  # the fine grid's degrees: (text, position)
        self._measured: frozenset[int] = frozenset()  # the stars the step shown measured
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
        self.h["grid_labels"] = [
            s.add_label(f"{NODES['grid_labels']}/{k}", text, position=_f32(p), font_screen_scale=0.8,
                        anchor="bottom-left")
            for k, (text, p) in enumerate(sky_grid_labels())]
        # the constellations: figures just inside the sphere (in front of the catalog's points), names
        figs = constellations()
        self.h["figures"] = s.add_line_segments(
            NODES["figures"], _f32(polylines_as_segments([ln * FIGURE_DEPTH for c in figs.values() for ln in c.lines])),
            FIGURE_RGB, thickness=1.2, thickness_units="screen")
        self.h["figure_names"] = [
            s.add_label(f"{NODES['figure_names']}/{c.abbr}", c.name, position=_f32(c.label_xyz * FIGURE_DEPTH),
                        font_screen_scale=0.75, anchor="center-center", visible=False)
            for c in figs.values()]
        # placed with the star names (`_place_names`): a constellation's name first, a star's name that would
        # overlap it hidden
        self._figure_names = (_name_plane(np.array([c.label_xyz for c in figs.values()])),
                              np.array([len(c.name) for c in figs.values()], dtype=np.float64))
        self._place_names()

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
            texts.append(f"{STAR_NAMES.get(hip, designation(hip))} {float(catalog.mag[i]):.1f}")
            names.append(s.add_label(f"{NODES['names']}/{hip}", texts[-1], position=_f32(catalog.xyz[i] * 1.0),
                                     font_screen_scale=0.85, anchor="top-left", visible=False))
        self.h["names"] = names
        self._names = (_name_plane(catalog.xyz[rows]), catalog.mag[rows],
                       np.array([len(t) for t in texts], dtype=np.float64))
        self._name_xyz = catalog.xyz[rows]
        self._place_names()

    def _place_names(self) -> None:
        """Show the constellations' names and the star names that do not overlap one placed before them at
        this zoom: the constellations' first, then the stars' by brightness (`present.place_labels`)."""
        figs = self.h.get("figure_names", []) if self._figure_names is not None else []
        stars = self.h.get("names", []) if self._names is not None else []
        fig_on = self.visible["constellations"] and bool(figs)
        parts = []  # (anchors, priority, lengths) of the names placed, constellations first
        if fig_on:
            fxy, fchars = self._figure_names
            parts.append((fxy, np.arange(len(fxy)) - 1e6, fchars))
        if stars:
            parts.append(self._names)
        keep = np.zeros(0, dtype=bool)
        if parts:
            span = REFERENCE_TAN * self.zoom ** (1.0 / 0.85)  # half-height of the view at the sphere (Session zoom)
            per_px = 2.0 * span / VIEW_HEIGHT_PX  # sphere units per screen pixel
            xy, priority, n_chars = (np.concatenate(a) for a in zip(*parts))
            w = (n_chars * NAME_CHAR_PX + NAME_PAD_PX) * per_px
            keep = place_labels(xy, priority, np.stack([w, np.full_like(w, NAME_HEIGHT_PX * per_px)], axis=1), gap=0.0)
        n_fig = len(figs) if fig_on else 0
        for k, hd in enumerate(figs):
            hd.visible = fig_on and bool(keep[k])
        if stars:
            self._name_keep = keep[n_fig:]
            for hd, k in zip(stars, self._name_keep):
                hd.visible = bool(k) and self.visible["names"]
            self._place_field_labels()

    def _place_field_labels(self) -> None:
        """Show the centroid numbers and the fine grid's degrees that overlap no label shown before them:
        the star names first, then the numbers (the step's stars, then the brightest), then the grid, on the
        plane of the image (the view down the boresight), sized for this zoom (`present.place_labels`)."""
        run, nums, grid = self._run, self.h.get("numbers", []), self.h.get("fine_labels", [])
        if run is None or run.R_shown is None:
            return
        R = run.R_shown
        per_px = 2.0 * REFERENCE_TAN * self.zoom ** (1.0 / 0.85) / VIEW_HEIGHT_PX  # image-plane units per pixel
        anchors, sizes, priority = [], [], []

        def add(xy, n_chars, scale, below, rank):  # below: the text hangs under its anchor (top-left)
            f = scale / 0.85 * per_px  # labels scale with their font
            w, h = (n_chars * NAME_CHAR_PX + NAME_PAD_PX) * f, NAME_HEIGHT_PX * f
            anchors.append((xy[0], xy[1] + (h if below else -h) / 2.0))
            sizes.append((w, h))
            priority.append(rank)

        if self._names is not None and self._name_keep is not None and self.visible["names"]:
            for v, k, n in zip(self._name_xyz @ R.T, self._name_keep, self._names[2]):
                if k and v[2] > 0.5:
                    add(v[:2] / v[2], n, 0.85, True, -2e3)
        for i, hd in enumerate(nums):  # beside the ring, on the image plane at IMAGE_DEPTH
            add(self._number_xy(i), len(hd.text), 0.7, False, i - 1e3 * (i in self._measured))
        for k, (text, p) in enumerate(self._grid_labels):
            add((R @ p)[:2] / max(float(R[2] @ p), 1e-6), len(text), 0.7, False, 1e3 + k)
        keep = place_labels(np.array(anchors).reshape(-1, 2), np.array(priority), np.array(sizes).reshape(-1, 2),
                            gap=0.0)[len(anchors) - len(nums) - len(self._grid_labels):]
        for hd, k in zip(nums, keep[:len(nums)]):
            hd.visible = bool(k) and self.visible["numbers"] and self.detail
        for hd, k in zip(grid, keep[len(nums):]):
            hd.visible = bool(k) and self.visible["grid"] and self.detail

    def _number_xy(self, i: int) -> np.ndarray:
        """Where centroid i's number is placed against the other labels, on the plane of the view down the boresight
        (a fisheye's star more than ~87 deg off its axis: far away, beside nothing)."""
        if self._mark_dirs is None:
            return (self._image_plane_xy[i] + np.array([0.8, -0.8]) * self._ring) / IMAGE_DEPTH
        d = self._mark_dirs[i]
        if not d[2] > 0.05:
            return np.array([1e6, 1e6])
        return d[:2] / d[2] + np.array([0.8, -0.8]) * self._ring

    def _rings(self, idx: np.ndarray, scale: float, depth: float) -> np.ndarray:
        """Segments of rings around the centroids idx, `scale` times the ring size, at `depth`: on the image plane
        (a pinhole's photograph) or on the sphere (a fisheye's)."""
        if self._mark_dirs is None:
            return ring_segments(self._image_plane_xy[idx], self._ring * scale, depth)
        return sky_ring_segments(self._mark_dirs[idx], self._ring * scale, depth)

    def _marks3(self, depth: float) -> np.ndarray:
        """The centroids as points (N, 3) of the camera frame at `depth`: on the image plane or on the sphere."""
        if self._mark_dirs is None:
            xy = self._image_plane_xy
            return np.concatenate([xy, np.full((len(xy), 1), depth)], axis=1)
        return self._mark_dirs * depth

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
        self._grid_labels = labels[:16]
        self.h["fine_labels"] = [
            s.add_label(f"{NODES['fine_labels']}/{k}", text, position=_f32(p), font_screen_scale=0.7,
                        anchor="bottom-left", visible=False)
            for k, (text, p) in enumerate(self._grid_labels)]

    # ------------------------------------------------------------------ camera
    def draw_run(self, run: Run, tex: np.ndarray | None, max_rings: int | None = None) -> None:
        """Camera(s), footprints, centroids and matches of a run; the step layer is reset. max_rings: ring
        only the brightest this many detections (a busy photograph stays readable; None: all)."""
        s = self.scene
        cam = run.source.camera
        R = run.R_shown
        for hd in self.h.pop("match_labels", []) + self.h.pop("numbers", []):
            hd.remove()
        for key in ("frustum", "centroids", "observed", "pattern", "true_frustum",  # children first
                    "camera", "true_camera", "footprint", "true_footprint", "matches", "match_stars"):
            if key in self.h:
                self.h.pop(key).remove()
        self._tex, self._sized["run"] = tex, []
        if R is None:  # an image that did not solve: no pose to draw it at
            for hd in self.h.pop("fine_labels", []):
                hd.remove()
            if "fine_grid" in self.h:
                self.h.pop("fine_grid").remove()
            self._grid_key, self._grid_labels = None, []
            self._run = None
            self.show_step(run, None)
            return
        catalog = run.catalog
        self._run = run
        self.draw_fine_grid(R[2], cam.fov_deg, 1.8 * cam.half_diagonal_rad)
        depth = IMAGE_DEPTH
        self.h["camera"] = s.add_frame(NODES["camera"], wxyz=pose_wxyz(R), position=(0.0, 0.0, 0.0), show_axes=False)
        color = EST_RGB if run.result.R is not None else TRUE_RGB
        if not cam.fisheye:
            self.h["frustum"] = s.add_camera_frustum(
                NODES["frustum"], fov=math.radians(cam.fov_v_deg), aspect=cam.width / cam.height,
                scale=frustum_scale(cam, depth), color=color, thickness=1.5, thickness_units="screen",
                image=tex if self.visible["image"] else None, format="jpeg", jpeg_quality=85)
        elif tex is not None:
            # a fisheye's photograph where its lens saw each pixel: a mesh over the sphere at `depth` (no frustum
            # holds a field of up to 240 deg), textured with the photograph as it is (`fisheye_photo_glb`)
            self.h["frustum"] = s.add_glb(NODES["frustum"], fisheye_photo_glb(cam, tex, depth),
                                          visible=self.visible["image"])
        border = polylines_as_segments([sensor_footprint(cam, R)])
        border = border[np.isfinite(border).all(axis=(1, 2))]  # (a fisheye's corners it does not see)
        self.h["footprint"] = s.add_line_segments(NODES["footprint"], _f32(border), color, thickness=2.0,
                                                  thickness_units="screen")
        # centroids: rings on the image plane (on the sphere, a fisheye's), coloured by outcome, numbered by brightness
        uv = run.result.centroids.uv
        if cam.fisheye:
            self._mark_dirs = cam.unproject(uv).reshape(-1, 3)
            self._image_plane_xy = np.zeros((len(uv), 2))  # (a pinhole's only)
            ring = RING_PX * max(cam.width, cam.height) / 1024.0 / cam.fx  # radians (fx: px per radian at its axis)
        else:
            self._mark_dirs = None
            self._image_plane_xy = image_plane_xy(cam, uv) * depth
            ring = RING_PX * max(cam.width, cam.height) / 1024.0 / cam.fx * depth
        self._ring = ring
        segs, cols = [], []
        for i, o in enumerate(run.outcomes[:max_rings]):
            rs = self._rings(np.array([i]), 1.0, depth * 0.9995)
            segs.append(rs)
            cols.append(np.broadcast_to(np.array(OUTCOME_RGB[o], np.uint8), rs.shape))
        self._ring_colors = None
        if segs:
            self._ring_colors = np.ascontiguousarray(np.concatenate(cols))  # at the end: coloured by outcome
            self.h["centroids"] = s.add_line_segments(NODES["centroids"], _f32(np.concatenate(segs)),
                                                      self._ring_colors, thickness=1.5, thickness_units="screen")
        at = self._marks3(depth * 0.999)
        lift = np.array([0.8, -0.8, 0.0]) * (ring * depth if cam.fisheye else ring)
        self.h["numbers"] = [
            s.add_label(f"{NODES['numbers']}/{i}", str(i), position=_f32(at[i] + lift), font_screen_scale=0.7,
                        anchor="bottom-left", visible=False)
            for i in range(min(len(at), 40))]
        self._place_field_labels()  # the numbers and the grid's degrees that overlap no other label
        if run.R_true is not None and run.result.R is not None:
            self.h["true_camera"] = s.add_frame(NODES["true_camera"], wxyz=pose_wxyz(run.R_true),
                                                position=(0.0, 0.0, 0.0), show_axes=False,
                                                visible=self.visible["true"])
            if not cam.fisheye:
                self.h["true_frustum"] = s.add_camera_frustum(
                    NODES["true_frustum"], fov=math.radians(cam.fov_v_deg), aspect=cam.width / cam.height,
                    scale=frustum_scale(cam, depth * 1.001), color=TRUE_RGB, thickness=1.0, thickness_units="screen")
            true_border = polylines_as_segments([sensor_footprint(cam, run.R_true)])
            self.h["true_footprint"] = s.add_line_segments(
                NODES["true_footprint"], _f32(true_border[np.isfinite(true_border).all(axis=(1, 2))]),
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
                                 f"{designation(catalog.hip[r])} {float(catalog.mag[r]):.1f}",
                                 position=_f32(catalog.xyz[r]), font_screen_scale=0.7, anchor="top-right")
            for r in rows[np.argsort(catalog.mag[rows])][:25]]

    # ------------------------------------------------------------------ steps
    def _ensure_step_nodes(self) -> None:
        """One node per step role of skyview.present.drawables (hidden until a step draws it)."""
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
            p3 = self._marks3(IMAGE_DEPTH * 0.999)
            for role in IMAGE_ROLES:
                hd = self.h[role]
                dr = d.drawables.get(role) if d is not None else None
                seg = np.zeros((0, 2, 3))
                if dr is not None and role == "pattern":
                    e = dr.edges[(dr.edges < len(p3)).all(axis=1)] if len(dr.edges) else dr.edges
                    if len(e):
                        seg = np.stack([p3[e[:, 0]], p3[e[:, 1]]], axis=1)
                elif dr is not None:
                    sel = dr.observed[dr.observed < len(p3)]
                    if len(sel):
                        seg = self._rings(sel, 1.7 if role == "observed" else 1.35, IMAGE_DEPTH * 0.999)
                if len(seg):
                    hd.points = _f32(seg)
                    hd.colors = np.broadcast_to(np.array(dr.color, np.uint8), seg.shape).copy()
                    hd.visible = True
                else:
                    hd.visible = False
        self._show_identification(d is None or d.final)
        measured = frozenset(int(i) for i in (d.observed if d is not None else ()))
        if measured != self._measured:  # the step's stars keep their numbers first
            self._measured = measured
            self._place_field_labels()
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
        self._place_field_labels()

    def set_visible(self, what: str, on: bool) -> None:
        self.visible[what] = bool(on)
        if what == "image" and "frustum" in self.h:
            if self._mark_dirs is not None:  # a fisheye's photograph: a mesh of its own, shown or hidden
                self.h["frustum"].visible = bool(on)
            else:
                self.h["frustum"].image = self._tex if on else None
        if what == "candidates":
            for key in SKY_ROLES:
                if key in self.h and not on:
                    self.h[key].visible = False
        if what in ("hips", "matches"):
            self._draw_match_labels()
        if what in ("names", "constellations"):  # the names that do not collide at this zoom
            self._place_names()
        groups = {
            "grid": ["grid", "grid_main", "grid_labels", "fine_grid", "fine_labels"],
            "constellations": ["figures"],  # its names: placed with the star names
            "stars": ["stars"],
            "true": ["true_camera", "true_footprint"],
            "matches": ["matches", "match_stars"] if self.final else [],
            "numbers": ["numbers"],
            "track": ["track", "track_labels"],
        }
        for key in groups.get(what, []):
            if key in ("numbers", "fine_labels"):  # placed with the names, in the view's plane
                continue
            hd = self.h.get(key)
            for one in (hd if isinstance(hd, list) else [hd] if hd is not None else []):
                one.visible = on
        if what in ("grid", "numbers"):
            self._place_field_labels()

    def show_pick(self, catalog: GuideCatalog, row: int | None, text: str = "") -> None:
        if "pick" in self.h:
            self.h.pop("pick").remove()
        if row is not None:
            self.h["pick"] = self.scene.add_label(NODES["pick"], text, position=_f32(catalog.xyz[row]),
                                                  font_screen_scale=0.95, anchor="bottom-left")
