"""The camera of one browser tab: where it looks, and the zoom that sizes the stars and labels.

The tab's camera sits at the sphere's centre. `point` looks down a run's boresight ('boresight' fits
the sensor in the view, 'wide' shows the sky around it, 'follow' keeps the zoom); `follow` does that
after each new run when the panel's "Follow the boresight" is ticked; `on_camera` handles the tab's
reports (its first size, a resize before the user moved, the user's zoom). Without a tab (a session
drawn for every tab, as in tests) there is no camera and these do nothing.
"""

from __future__ import annotations

import math

import numpy as np

from skyview.core.camera import Camera
from skyview.viewer.run import Run

WIDE_FOV_DEG = 70.0
# the widest view fitted to a sensor: a perspective view from the sphere's centre shows at most this much (a fisheye's
# 120-240 deg would need a view of 180 deg or more, which draws nothing): an all-sky frame's middle, zoom out for more
MAX_FIT_FOV_DEG = 120.0
REFERENCE_TAN = math.tan(math.radians(30.0))  # star sizes are tuned for a 60-degree view


class CameraControl:
    """client: a viser `ClientHandle` (or None); sky: the tab's `SkyScene`; lock, atomic: the session's."""

    def __init__(self, client, sky, lock, atomic):
        self.client = client
        self.atomic = atomic  # the owner's atomic(): scene changes sent together
        self.sky = sky
        self.lock = lock
        self._pending: tuple[str, np.ndarray] | None = None  # a view asked for before the tab reported its size
        self._applied: tuple | None = None  # (mode, R, run, page size, fov) of the last view set
        self._zoom = 1.0
        self._boresight: np.ndarray | None = None  # of the last run followed
        self._sensor: Camera | None = None

    @property
    def fov_rad(self) -> float:
        """The tab's vertical field of view (60 degrees without a tab)."""
        return self.client.camera.fov if self.client is not None else math.radians(60.0)

    def point(self, mode: str, run: Run | None) -> None:
        """Look down the run's boresight ('boresight', 'wide' or 'follow')."""
        R = run.R_shown if run is not None else None
        if R is None or self.client is None:
            return
        cam = self.client.camera
        if cam._state.update_timestamp == 0.0 or not cam.image_height:  # the tab has not reported its view yet
            self._pending = (mode, R)
            return
        self._apply(mode, R, run)

    def follow(self, run: Run) -> None:
        """After a new run: fit a new sensor in the view, follow a pointing that moved (keeping the zoom)."""
        R = run.R_shown
        if R is None:
            return
        cam = run.source.camera
        if self._boresight is None or cam != self._sensor:
            self.point("boresight", run)  # first run, or another sensor: fit it in the view
        elif float(self._boresight @ R[2]) < math.cos(math.radians(0.25 * run.source.fov_deg)):
            self.point("follow", run)  # the pointing moved: follow it, keep the zoom
        self._boresight, self._sensor = R[2].copy(), cam

    def _apply(self, mode: str, R: np.ndarray, run: Run) -> None:
        cam, camera = self.client.camera, run.source.camera
        if mode == "boresight":
            aspect = cam.image_width / cam.image_height
            half_v = math.radians(camera.fov_v_deg) / 2.0
            half_h = math.radians(camera.fov_deg) / 2.0
            fov = 2.0 * math.atan(1.2 * max(math.tan(min(half_v, 1.5)), math.tan(min(half_h, 1.5)) / aspect))
            fov = min(fov, math.radians(MAX_FIT_FOV_DEG))
        elif mode == "wide":
            fov = math.radians(WIDE_FOV_DEG)
        else:
            fov = cam.fov
        with self.client.atomic():
            cam.position = (0.0, 0.0, 0.0)
            cam.look_at = tuple(R[2])
            cam.up_direction = tuple(-R[1])
            cam.fov = fov
        self._applied = (mode, R, run, (cam.image_width, cam.image_height), fov)
        self.set_zoom(cam.fov, 1.0, run)

    def on_camera(self, cam, run: Run | None) -> None:
        """The tab reported its camera: apply a pending view, refit after a resize, or follow the zoom."""
        if self._pending is not None and run is not None and cam.image_height:
            mode, R = self._pending
            self._pending = None
            self._apply(mode, R, run)
            return
        applied = self._applied
        if applied is not None and applied[0] == "boresight" and (cam.image_width, cam.image_height) != applied[3]:
            untouched = (abs(cam.fov - applied[4]) < 1e-6 and np.linalg.norm(cam.position) < 1e-9
                         and np.allclose(cam.look_at, applied[1][2], atol=1e-9))
            if untouched:  # the page changed size before the user moved: fit the sensor again
                self._apply("boresight", applied[1], applied[2])
                return
        dist = float(np.linalg.norm(np.asarray(cam.look_at) - np.asarray(cam.position)))
        self.set_zoom(cam.fov, dist, run)

    def set_zoom(self, fov: float, dist: float, run: Run | None) -> None:
        """Keep stars alike at every zoom; show the field's small labels only when it fills the view."""
        span = math.tan(fov / 2.0) * max(dist, 0.05)  # half-height of the view at the sphere
        z = max(0.03, min(3.0, span / REFERENCE_TAN)) ** 0.85
        detail = run is None or span < 3.0 * math.tan(math.radians(run.source.camera.fov_v_deg) / 2.0)
        if abs(math.log(z / self._zoom)) > 0.1 or detail != self.sky.detail:
            self._zoom = z
            with self.lock, self.atomic():
                self.sky.set_zoom(z)
                self.sky.set_detail(detail)
