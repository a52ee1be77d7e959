"""skyview: where is the star tracker pointing?

centroids -> star identification against the Hipparcos catalog -> attitude, with a simulator for
known truth and a record of every step each method takes.

The public API::

    import skyview
    sol = skyview.solve("photo.jpg")             # blind: no field of view needed
    if sol.solved:
        print(sol.ra_deg, sol.dec_deg, sol.roll_deg, sol.fov_deg)

:func:`solve` returns a :class:`Solution` (frozen; ``R`` maps ICRS to the OpenCV camera frame,
``quaternion`` is scalar first ``[w, x, y, z]``, ``roll_deg`` is image-up from north towards east,
``fov_deg`` is horizontal). :class:`Solver` solves many images with the same settings.
:func:`solve_image` is the older call that returns the pipeline's ``SolveResult``.
"""

from __future__ import annotations

__version__ = "0.1.0"

import os as _os
from typing import TYPE_CHECKING, Any

# formats whose size skyview cannot read from the header are still bounded by OpenCV's own limit
_os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(100_000_000))

from skyview.core.errors import BadInput, SkyviewError  # noqa: E402

if TYPE_CHECKING:  # the API module is imported on first use: `import skyview` (and the CLI) stay fast
    from pathlib import Path

    import numpy as np

    from skyview.solver.api import Match, NotSolvedError, Solution, Solver, solve
    from skyview.solver.pipeline import SolveResult

__all__ = ["solve", "Solver", "Solution", "Match", "NotSolvedError", "SkyviewError", "BadInput", "solve_image",
           "__version__"]

_API_NAMES = ("solve", "Solver", "Solution", "Match", "NotSolvedError")


def __getattr__(name: str) -> Any:
    if name in _API_NAMES:
        from skyview.solver import api
        value = getattr(api, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'skyview' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


def solve_image(image: str | Path | np.ndarray, fov_deg: float | None = None, method: str | None = None,
                **kwargs: Any) -> SolveResult:
    """Image to attitude, as the pipeline's ``SolveResult``; see :func:`skyview.solver.pipeline.solve_image`.

    The older call, kept as it was; :func:`solve` is the typed API (a :class:`Solution`)."""
    from skyview.solver.pipeline import solve_image as _solve

    return _solve(image, fov_deg, method, **kwargs)
