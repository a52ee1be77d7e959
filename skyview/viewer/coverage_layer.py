"""The sky-coverage layer of the viewer: a sweep's map (`skyview coverage`) as a coloured sphere.

What is drawn (viser scene API): the HEALPix pixels of the sweep (`coverage_map.sphere_mesh`, the
same geometry and colours as the .rrd) just inside the unit celestial sphere, one
`scene.add_mesh_simple` per colour band (viser gives a mesh one colour: the solved share is cut into
BANDS bands, each drawn in its mid colour, viridis: dark = never solved, yellow = always), double
sided so it reads from inside the sphere, half transparent over the stars; and one `scene.add_label`
at the north pole with the sweep's method, FOV, depth and coverage, and a warning when the FOV the
viewer is looking at differs from the sweep's.

Self-contained: `CoverageLayer.from_folder(DIR).show(server.scene, fov_deg=...)` adds it,
`.hide()` removes it. The hook for the viewer: a panel checkbox "Sky coverage (DIR)" that calls
show / hide, and `skyview view --coverage DIR` that loads the layer at start.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skyview.bench.coverage import CoverageConfig
from skyview.bench.coverage_map import colours, load_map, map_nside, sphere_mesh

NODE = "/coverage"
BANDS = 8
RADIUS = 0.985  # inside the unit sphere, under the stars and the footprints
OPACITY = 0.55


@dataclass
class CoverageLayer:
    config: CoverageConfig
    solved: np.ndarray  # per HEALPix pixel (map nside), NaN where the sweep has no orientation
    summary: dict
    handles: list = field(default_factory=list)
    caption: str = ""

    @classmethod
    def from_folder(cls, folder: str | Path) -> "CoverageLayer":
        cfg, px, summary = load_map(folder)
        return cls(cfg, px["solved"], summary)

    @property
    def label(self) -> str:
        """The View tab's checkbox for this layer."""
        return f"Sky coverage: {self.config.method}, {self.config.fov_deg:g}°"

    @property
    def visible(self) -> bool:
        return bool(self.handles)

    def show(self, scene, fov_deg: float | None = None) -> None:
        """Add the coloured sphere and its caption to a viser scene (replacing a shown one)."""
        self.hide()
        v, t, _ = sphere_mesh(map_nside(self.config), self.solved, radius=RADIUS)
        per_pixel = len(t) // len(self.solved)
        band = np.clip(np.floor(np.nan_to_num(self.solved, nan=-1.0) * BANDS), -1, BANDS - 1).astype(int)
        for b in range(-1, BANDS):
            rows = np.flatnonzero(band == b)
            if len(rows) == 0:
                continue
            tri = t.reshape(len(self.solved), per_pixel, 3)[rows].reshape(-1, 3)
            used, inverse = np.unique(tri, return_inverse=True)
            mid = np.nan if b < 0 else (b + 0.5) / BANDS
            rgb = tuple(int(x) for x in colours(np.array([mid]))[0])
            self.handles.append(scene.add_mesh_simple(
                f"{NODE}/band{b + 1}", v[used], inverse.reshape(-1, 3).astype(np.int32), color=rgb,
                opacity=OPACITY, side="double", flat_shading=True, cast_shadow=False, receive_shadow=False))
        s, cfg = self.summary, self.config
        self.caption = (f"coverage: {cfg.method} ({cfg.variant}), {cfg.fov_deg:g} deg FOV, Hp <= {cfg.mag_limit:g}: "
                        f"{s['coverage_pct']:.1f} % of {s['orientations']} orientations solved, "
                        f"{s['counts']['wrong']} wrong")
        if fov_deg is not None and abs(float(fov_deg) - cfg.fov_deg) > 1e-6:
            self.caption += f" (the view's FOV is {float(fov_deg):g} deg: this map is for {cfg.fov_deg:g} deg)"
        self.handles.append(scene.add_label(f"{NODE}/caption", self.caption, position=(0.0, 0.0, 1.02),
                                            font_screen_scale=0.8, anchor="bottom-center"))

    def hide(self) -> None:
        """Remove everything the layer added."""
        for h in self.handles:
            h.remove()
        self.handles = []
