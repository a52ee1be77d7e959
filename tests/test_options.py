"""Solve options no camera or sky can have are refused in one line before any work."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from skyview.core.errors import BadInput
from skyview.solver.pipeline import solve_image

PHOTO = sorted((Path(__file__).parent / "data" / "real-images").glob("*.png"))[0]


@pytest.mark.parametrize("options, words", [
    ({"max_stars": 0}, "at least 3 stars"),
    ({"max_stars": -3}, "at least 3 stars"),
    ({"max_stars": 2.5}, "whole number"),
    ({"mag_limit": 30.0}, "outside the sky"),
    ({"mag_limit": -40.0}, "outside the sky"),
    ({"mag_limit": float("nan")}, "not a finite number"),
    ({"distortion": (5.0, 0.0)}, "beyond any lens"),
    ({"distortion": (0.0, float("inf"))}, "not a finite number"),
    ({"epoch": 1e9}, "epoch"),
    ({"memory_mb": 0}, "must be positive"),
    ({"memory_mb": -1}, "must be positive"),
])
def test_impossible_solve_options_are_bad_input(options, words):
    # refused before the image is even read: a blank array would otherwise say "no stars"
    with pytest.raises(BadInput, match=words):
        solve_image(np.zeros((64, 64), np.uint8), **options)


@pytest.mark.parametrize("args", [["--max-stars", "-3"], ["--mag-limit", "30"], ["--epoch", "1e9"],
                                  ["--memory-mb", "0"], ["--distortion", "5", "5"]])
def test_cli_refuses_impossible_options_with_one_json_object(args):
    out = subprocess.run([sys.executable, "-m", "skyview", "solve", str(PHOTO), "--json", *args],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert json.loads(out.stdout)["status"] == "error"
