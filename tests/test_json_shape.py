"""One JSON shape for a solution wherever it appears (issue 28, item 3): `solve --json`, each line of
`solve-sequence --json` (solved, failed and unreadable frames alike), the API's `Solution.to_json()`."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import skyview
from skyview.cli import main
from skyview.solver.solution_json import SOLUTION_KEYS

PHOTOS = sorted((Path(__file__).parent / "data" / "real-images").glob("*.png"))


def _head(d: dict) -> tuple:
    return tuple(d)[: len(SOLUTION_KEYS)]


def test_solve_sequence_and_api_give_one_shape(tmp_path, capsys):
    photo = PHOTOS[0]
    assert main(["solve", str(photo), "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    assert _head(cli) == SOLUTION_KEYS
    assert cli["solved"] and cli["reason"] == "" and len(cli["R"]) == 3 and len(cli["quaternion"]) == 4
    assert cli["distortion"].keys() == {"k1", "k2"} and cli["sigma_arcsec"].keys() == {"boresight", "roll"}
    assert 0.0 <= cli["p_false"] < 1e-6 and cli["n_matches"] == len(cli["matches"]) >= 20
    assert all(m["name"] == f"HIP {m['hip']}" for m in cli["matches"])

    api = json.loads(skyview.solve(str(photo)).to_json())
    assert tuple(api) == SOLUTION_KEYS
    for key in ("R", "quaternion", "ra_deg", "dec_deg", "roll_deg", "fov_deg", "distortion", "mag_limit", "p_false"):
        np.testing.assert_allclose(np.asarray(api[key] if key != "distortion" else list(api[key].values())),
                                   np.asarray(cli[key] if key != "distortion" else list(cli[key].values())),
                                   rtol=1e-12, err_msg=key)
    assert [m["hip"] for m in api["matches"]] == [m["hip"] for m in cli["matches"]]

    # a sequence: two photographs and an unreadable frame between them
    frames = [tmp_path / "f0.png", tmp_path / "f1.png", tmp_path / "f2.png"]
    shutil.copy(PHOTOS[0], frames[0])
    frames[1].write_bytes(b"not an image")
    shutil.copy(PHOTOS[1], frames[2])
    assert main(["solve-sequence", *map(str, frames), "--json"]) == 1
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines() if x.strip()]
    assert [d["status"] for d in lines] == ["solved", "error", "solved"]
    for d in lines:
        assert d["frame"] in (0, 1, 2) and _head({k: v for k, v in d.items() if k not in ("frame", "image")}) \
            == SOLUTION_KEYS
    assert lines[1]["R"] is None and lines[1]["reason"] == lines[1]["error"] and not lines[1]["solved"]
    first = lines[0]
    # the same attitude (the tracker takes it from the matches in its own catalog, to Hp 6: within a pixel)
    dR = np.asarray(first["R"]) @ np.asarray(cli["R"]).T
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) * 3600 < 120
    assert first["method"] == "blind" and first["camera_fitted"] and first["fov_deg"] == pytest.approx(cli["fov_deg"])


def test_a_failed_solve_has_the_same_keys_with_no_values(tmp_path, capsys):
    noise = tmp_path / "noise.png"
    import cv2

    cv2.imwrite(str(noise), np.random.default_rng(0).integers(0, 40, (300, 400), dtype=np.uint8))
    assert main(["solve", str(noise), "--json", "--no-deep"]) == 1
    d = json.loads(capsys.readouterr().out)
    assert _head(d) == SOLUTION_KEYS
    assert d["status"] == "failed" and not d["solved"] and d["reason"]
    assert d["R"] is None and d["quaternion"] is None and d["ra_deg"] is None and d["p_false"] is None
    assert d["sigma_arcsec"] == {"boresight": None, "roll": None} and d["matches"] == [] and d["n_matches"] == 0


@pytest.mark.slow
def test_the_viewers_download_is_the_same_shape():
    from helpers import viewer_session

    photo = PHOTOS[0]
    import cv2

    with viewer_session() as (server, s):
        s.receive_upload(photo.name, cv2.imencode(".png", cv2.imread(str(photo), cv2.IMREAD_UNCHANGED))[1].tobytes())
        assert s.wait_idle(120) and s.error == ""
        name, text = s.result_json()
    d = json.loads(text)
    assert name == photo.stem + "-skyview.json" and _head(d) == SOLUTION_KEYS
    api = json.loads(skyview.solve(str(photo)).to_json())
    np.testing.assert_allclose(d["R"], api["R"], atol=1e-12)
    assert d["solved"] and d["image"] == photo.name and d["n_matches"] == api["n_matches"]
