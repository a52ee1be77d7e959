"""A negative of the sky (dark stars on a bright background, an inverted export): recognised and solved inverted,
with a note; a sky as it is is never taken for one."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from skyview.core.attitude import attitude_error_arcsec
from skyview.detect.centroids import load_image
from skyview.solver.pipeline import NEGATIVE_NOTE, looks_negative, solve_image

REAL = Path(__file__).parent / "data" / "real-images"
REFERENCE = json.loads((REAL / "reference.json").read_text())


def test_a_negative_photograph_solves_inverted_and_a_positive_one_is_never_a_negative():
    names = sorted(REFERENCE)
    for name in names:
        img = load_image(REAL / name)
        assert not looks_negative(img) and looks_negative(65535 - img), name
    name = names[0]
    img = load_image(REAL / name)
    for neg in (65535 - img, (255 - (img >> 8)).astype(np.uint8)):  # 16-bit, and 8-bit as an export would be
        res = solve_image(neg, deep=False)
        assert res.solved and NEGATIVE_NOTE in res.notes, res.reason
        assert attitude_error_arcsec(res.R, np.array(REFERENCE[name]["R"]))["boresight"] < 60.0
    assert not solve_image(65535 - img, deep=False, negative=False).solved
