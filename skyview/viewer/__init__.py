"""The browser viewer (`skyview view`): celestial sphere, field of view, sensor image, steps, live in viser.

Modules: `run` (simulate / solve / compare through the pipeline's `Solver`), `sequence_run` (sequences of
frames for a method that identifies over them: the stochastic one), `steps` (steps and results
-> drawable geometry, no viewer), `picture` (the sensor image for display), `scene` (the 3-D scene),
`panel` (the side panel's widgets and text), `session` (one per browser tab: wiring, camera, jobs),
`worker` (its background thread), `app` (the server and `skyview view`).
See docs/viewer.md.
"""

from skyview.viewer.app import ViewerApp, serve
from skyview.viewer.session import Session

__all__ = ["Session", "ViewerApp", "serve"]
