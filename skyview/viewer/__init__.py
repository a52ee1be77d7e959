"""The browser viewer (`skyview view`): celestial sphere, field of view, sensor image, steps, live in viser.

Modules: `run` (simulate / solve / compare through the pipeline's `MethodSolver`), `sequence_run` (sequences of
frames: a method that identifies over them, or tracking), `picture` (the sensor image for display),
`geometry` (pure functions on the sphere), `scene` (the 3-D scene), `panel` (the side panel's widgets and
text), `state` (what a tab shows), `player` (steps and frames played), `plot_control` and `camera_control`
(the plots and the tab's camera), `session` (one per browser tab: the coordinator), `worker` (its
background thread), `app` (the server and `skyview view`).
See docs/viewer.md.
"""

from skyview.viewer.app import ViewerApp, serve
from skyview.viewer.session import Session

__all__ = ["Session", "ViewerApp", "serve"]
