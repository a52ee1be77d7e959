"""skyview: where is the star tracker pointing?

centroids -> star identification against the Hipparcos catalog -> attitude, with a simulator for
known truth and a record of every step each method takes.
"""

__version__ = "0.1.0"

import os as _os

# formats whose size skyview cannot read from the header are still bounded by OpenCV's own limit
_os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(100_000_000))

from skyview.errors import SkyviewError, BadInput  # noqa: E402,F401


def solve_image(*args, **kwargs):
    """Image to attitude; see :func:`skyview.pipeline.solve_image`."""
    from skyview.pipeline import solve_image as _solve

    return _solve(*args, **kwargs)
