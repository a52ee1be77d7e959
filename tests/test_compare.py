"""skyview bench --compare: every method on the same images, scored alike (skyview.bench.compare)."""

from __future__ import annotations

import json

import pytest

from skyview.bench.compare import (
    REAL_IMAGES,
    STAR_BINS,
    format_markdown,
    run_real,
    run_simulated,
    save_compare,
    star_bin,
)
from skyview.cli import main
from skyview.core.errors import BadInput
from skyview.simulate.scenarios import SCENARIOS


def test_star_bins_cover_every_count():
    labels = [star_bin(k) for k in range(0, 40)]
    assert labels[:4] == ["0-3"] * 4 and labels[4] == "4" and labels[9] == "8-10" and labels[30] == "11+"
    assert [b[2] for b in STAR_BINS] == sorted(set(labels), key=labels.index)


def test_every_method_sees_the_same_images(tmp_path):
    sim = run_simulated(SCENARIOS["cole8"], 3, 7, n_slow=1, methods=("angle", "svd"),
                        variants=("paper", "improved"), slow=("svd",))
    rows = {(r["method"], r["variant"]): r for r in sim["rows"]}
    assert set(rows) == {("angle", "paper"), ("angle", "improved"), ("svd", "paper"), ("svd", "improved")}
    assert rows["angle", "paper"]["n"] == 3 and rows["svd", "paper"]["n"] == 1  # a slow method: the first image
    for r in sim["rows"]:
        assert r["correct"] + r["inconclusive"] + r["incorrect"] == r["n"]
        assert sum(b["trials"] for b in r["by_stars"].values()) == r["n"]
        assert r["incorrect"] == 0
    # the same fields: the same stars in every bin for both variants
    assert rows["angle", "paper"]["by_stars"].keys() == rows["angle", "improved"]["by_stars"].keys()
    assert ([b["trials"] for b in rows["angle", "paper"]["by_stars"].values()]
            == [b["trials"] for b in rows["angle", "improved"]["by_stars"].values()])
    report = {"kind": "compare", "version": 1, "simulated": sim, "machine": {}, "wall_s": 1.0}
    md = format_markdown(report)
    assert "| angle | improved | 3 |" in md and "| svd | paper | 1 |" in md
    j, m = save_compare(report, tmp_path, "cmp")
    assert json.loads(j.read_text())["simulated"]["rows"][0]["method"] == "angle" and m.read_text() == md


def test_real_photographs_calibrated():
    name = sorted(json.loads((REAL_IMAGES / "reference.json").read_text()))[0]
    real = run_real(methods=("svd",), variants=("improved",), blind=False, names=[name])
    (row,) = real["rows"]
    assert real["images"] == 1 and row["correct"] + row["wrong"] + row["inconclusive"] == 1
    assert row["wrong"] == 0 and set(row["per_image"]) == {name}
    with pytest.raises(BadInput, match="reference.json"):
        run_real(REAL_IMAGES.parent, methods=("svd",))


def test_cli_refuses_what_compare_sets_itself(capsys):
    assert main(["bench", "--compare", "--method", "angle"]) == 2
    err = capsys.readouterr().err
    assert "--compare runs every method" in err and "Traceback" not in err
