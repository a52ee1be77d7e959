"""Recordings of frame sequences (the stochastic method): written, read back with rerun-sdk's reader and
checked against the SequenceResult and the simulator's truth; the CLI; the committed example; rendered."""

from __future__ import annotations

import json
from collections import defaultdict

import numpy as np
import pytest
from rerun.chunk import RrdReader
from test_record import REPO, _open, needs_lavapipe, one_line_error, read, strict_rerun, viewer  # noqa: F401, F811

from skyview.cli import main
from skyview.core.errors import BadInput
from skyview.record import examples as record_examples
from skyview.record import sequence as rs
from skyview.simulate.render import save_sequence

EXAMPLE = REPO / "recordings" / "stochastic-udomkesmalee30.rrd"
ARCSEC = np.pi / 180 / 3600


def per_frame(entity: dict, name: str) -> dict[int, list]:
    """Values of one component column by `frame` time (rows in the order logged; a Clear row gives None)."""
    out: dict[int, list] = defaultdict(list)
    for b in entity["batches"]:
        if "frame" not in b.schema.names:
            continue
        frames = b.column("frame").to_pylist()
        vals = b.column(name).to_pylist() if name in b.schema.names else [None] * b.num_rows
        for f, v in zip(frames, vals):
            out[f].append(v)
    return dict(out)


def last(entity: dict, name: str) -> dict[int, object]:
    """The value each frame ends on (latest at that frame)."""
    return {f: v[-1] for f, v in per_frame(entity, name).items()}


@pytest.fixture(scope="module")
def runner():
    return rs.PaperSequenceRunner()


@pytest.fixture(scope="module")
def paper(runner, tmp_path_factory):
    """Run 0 of the paper's experiment at 10 arcsec, bench seed 0: identified at its last frame."""
    case = runner.run(0)
    assert case.result.solved and case.outcome == "correct", case.result.identifications[-1].reason
    path = tmp_path_factory.mktemp("seq") / "stochastic-udomkesmalee30-0.rrd"
    info = runner.record(case, path)
    return case, path, info, read(path)


# ============================================================================ contents

def test_frame_and_step_timelines(paper):
    case, path, info, ents = paper
    ids = case.result.identifications
    K = len(ids)
    steps = [s for r in ids for s in r.steps]
    assert info.frames == K == 5 and info.steps == len(steps) and info.frame == case.result.frame == 4
    assert info.identified == [k for k, r in enumerate(ids) if r.identified]
    assert len(RrdReader(path).recordings()) == 1
    # the frame timeline holds exactly the sequence's frames: one image per frame
    frames = {f for e in ents.values() for b in e["batches"] if "frame" in b.schema.names
              for f in b.column("frame").to_pylist()}
    assert frames == set(range(K))
    img = ents["/camera/image"]
    assert img["timelines"] == {"frame", "step"}
    assert sorted(per_frame(img, "EncodedImage:blob")) == list(range(K))
    assert all(len(v) == 1 for v in per_frame(img, "EncodedImage:blob").values())
    # the step timeline runs on across frames, each step at its own frame
    log = ents["/steps/log"]
    got = []
    for b in log["batches"]:
        got += list(zip(b.column("step").to_pylist(), b.column("frame").to_pylist(),
                        [t[0].split("\n")[0] for t in b.column("TextLog:text").to_pylist()]))
    got.sort()
    want = [(i, k, f"[{s.kind}] {s.note}") for i, (k, s) in enumerate((k, s) for k, r in enumerate(ids) for s in r.steps)]
    assert got == want
    for e in ("/sky/catalog", "/sky/grid", "/sky/path/true", "/result", "/camera/image"):  # the pinhole
        assert ents[e]["static"], e
    assert not ents["/sky/catalog"]["timelines"] and not ents["/result"]["timelines"]


def test_posterior_series_are_the_results(paper):
    case, _, _, ents = paper
    ids = case.result.identifications
    scored = case.result.truth_figures()  # the truth, scored by skyview.simulate.scoring (not in the method's stats)
    for path_, (key, _, _) in rs.SERIES.items():
        got = last(ents[f"/{path_}"], "Scalars:scalars")
        want = {k: {**r.stats, **scored[k]}[key] for k, r in enumerate(ids)}
        assert sorted(got) == sorted(want), path_
        np.testing.assert_allclose([got[k][0] for k in sorted(got)], [want[k] for k in sorted(want)], rtol=1e-12)
    tp = [f["true_posterior"] for f in scored]
    assert tp[-1] > 0.95 and tp[0] < 0.05  # the posterior converges over the frames
    assert [r.stats["above_prior"] for r in ids][-1] <= 2
    # the legend: each series named once, statically
    names = [b.column("SeriesLines:names").to_pylist() for b in ents[f"/{rs.TRUE_POSTERIOR}"]["batches"]
             if "SeriesLines:names" in b.schema.names]
    assert names == [[["true star"]]]


def test_same_as_run_0_of_the_bench(paper):
    """`skyview record --method stochastic --seed S` is run 0 of `bench-sequence --noise-arcsec 10 --seed S`."""
    from skyview.bench.sequence import bench_sequence
    from skyview.simulate.scenarios import get_scenario

    case = paper[0]
    b = bench_sequence(get_scenario("udomkesmalee30"), 1, position_noise_rad=10 * ARCSEC, seed=0, progress=False)
    assert b["run0"]["true_posterior"] == [f["true_posterior"] for f in case.result.truth_figures()]
    assert b["run0"]["above_prior"] == [r.stats["above_prior"] for r in case.result.identifications]
    assert b["runs"][0]["seed"] == case.run_seed


def test_camera_pose_per_frame(paper):
    case, _, _, ents = paper
    ids = case.result.identifications
    truths = [f.truth for f in case.sim.frames]
    poses = last(ents["/camera"], "Transform3D:mat3x3")
    true_poses = last(ents["/truth/camera"], "Transform3D:mat3x3")
    assert sorted(poses) == sorted(true_poses) == list(range(len(ids)))
    for k, r in enumerate(ids):
        M = np.array(poses[k]).reshape(3, 3).T  # stored column-major
        T = np.array(true_poses[k]).reshape(3, 3).T
        np.testing.assert_allclose(T, truths[k]["R"], atol=1e-6)
        if r.identified:  # the identified frame: its estimated attitude, not the true one
            np.testing.assert_allclose(M, r.R, atol=1e-6)
            assert np.abs(M - T).max() > 1e-7
        else:
            np.testing.assert_allclose(M, truths[k]["R"], atol=1e-6)
    # footprint at the estimated attitude only where the frame was identified (cleared elsewhere)
    fov = last(ents["/sky/fov/estimated"], "LineStrips3D:strips")
    assert [k for k in sorted(fov) if fov[k]] == [k for k, r in enumerate(ids) if r.identified]
    matches = last(ents["/sky/matches/labels"], "Points3D:labels")
    k_id = case.result.frame
    cat = case.result.catalog
    # labels beside the matched stars, the brightest that do not collide
    assert set(matches[k_id]) <= {f"HIP {int(cat.hip[c])} (#{o})" for o, c in sorted(ids[k_id].matches.items())}
    assert len(matches[k_id]) >= min(4, len(ids[k_id].matches))
    assert all(not matches[k] for k in matches if k != k_id and not ids[k].identified)


def test_designated_hypotheses_and_truth(paper):
    case, _, _, ents = paper
    res = case.result
    cat = res.catalog
    rings = last(ents["/camera/image/designated"], "LineStrips2D:strips")
    hyp_pos = last(ents["/sky/hypotheses"], "Points3D:positions")
    hyp_rad = last(ents["/sky/hypotheses"], "Points3D:radii")
    hyp_lab = last(ents["/sky/hypotheses"], "Points3D:labels")
    true_ring = last(ents["/sky/true_designated"], "LineStrips3D:strips")
    true_lab = last(ents["/sky/true_designated"], "LineStrips3D:labels")
    for k, r in enumerate(res.identifications):
        st = {**r.stats, **res.truth_figures()[k]}
        d = st["designated"]
        ring = np.array(rings[k][0])
        np.testing.assert_allclose(ring[:-1].mean(axis=0), res.centroids[k].uv[d] + 0.5,
                                   atol=1e-3)  # ringed where it is (Rerun's pixel centres are at +0.5)
        top = st["top_rows"]
        np.testing.assert_allclose(np.array(hyp_pos[k]), cat.xyz[top], atol=1e-6)
        assert hyp_lab[k][0] == f"HIP {st['top_hips'][0]}: {st['posterior_top'][0]:.3f}"
        radii = np.array(hyp_rad[k])
        assert np.all(np.diff(radii) <= 1e-9)  # sized by posterior, largest first
        # the true designated star: ringed on the sphere around its catalog direction
        c = np.array(true_ring[k][0])[:-1].mean(axis=0)
        assert np.degrees(np.arccos(np.clip(c / np.linalg.norm(c) @ cat.xyz[st["true_row"]], -1, 1))) < 0.01
        assert true_lab[k] == [f"true: HIP {int(cat.hip[st['true_row']])}"]
    # the last frame's leading hypothesis is large and gold, the first frame's small and dim
    r_last, r_first = np.array(hyp_rad[4])[0], np.array(hyp_rad[0])[0]
    assert r_last > 3 * r_first


def test_result_document(paper):
    case, _, _, ents = paper
    text = [b.column("TextDocument:text").to_pylist() for b in ents["/result"]["batches"]][0][0][0]
    assert text.startswith("# stochastic (paper): sequence of 5 frames, identified at frame 4")
    for piece in ("10 arcsec", "the paper's \"10\" read as arcseconds", "## Frames", "## Attitude (estimated, frame 4)",
                  "## Truth", "wrong matches: **0**", "error: boresight", "Betelgeuse", "run 0 of skyview bench-sequence",
                  "| 0 | 27 |", "paper: above 1/N"):
        assert piece in text, piece
    for k, f in enumerate(case.result.truth_figures()):
        assert f"| {k} |" in text and f"{f['true_posterior']:.3f}" in text


def test_without_truth_or_images_centroids(paper, tmp_path):
    """A result solved from observation vectors without truth: the centroids are the observations, no truth
    entities, and the frames before the identified one get its attitude carried back by the known turns."""
    import dataclasses

    case = paper[0]
    sim = case.sim
    res = dataclasses.replace(case.result, centroids=None, truth=None, true_R=None,
                              identifications=[dataclasses.replace(r, stats={k: v for k, v in r.stats.items()
                                                                             if not k.startswith("true")})
                                               for r in case.result.identifications])
    turns = [sim.dR_cam(k) for k in range(len(sim.frames) - 1)]
    info = rs.record_sequence(tmp_path / "nt.rrd", res, [f.image for f in sim.frames], turns=turns)
    ents = read(tmp_path / "nt.rrd")
    assert info.frames == 5 and info.frame == 4
    assert not any(k.startswith(("/truth", "/camera/image/truth", "/sky/fov/true", "/sky/path", "/sky/true"))
                   for k in ents)
    assert f"/{rs.TRUE_POSTERIOR}" not in ents and f"/{rs.TOP_POSTERIOR}" in ents
    poses = last(ents["/camera"], "Transform3D:mat3x3")
    for k, f in enumerate(sim.frames):  # carried from frame 4 by the gyro turns: within arcseconds of the truth
        M = np.array(poses[k]).reshape(3, 3).T
        ang = np.degrees(np.arccos(np.clip((np.trace(M @ f.R.T) - 1) / 2, -1, 1))) * 3600
        assert ang < 300, (k, ang)
    cents = last(ents["/camera/image/centroids"], "Points2D:positions")
    np.testing.assert_allclose(np.array(cents[2]), res.observations[2].uv + 0.5, atol=1e-3)
    text = [b.column("TextDocument:text").to_pylist() for b in ents["/result"]["batches"]][0][0][0]
    assert "carried from frame 4" in text and "## Truth" not in text


def test_bad_input_is_one_line_and_overwrites_nothing(paper, tmp_path):
    case = paper[0]
    images = [f.image for f in case.sim.frames]
    with pytest.raises(BadInput, match="5 images|4 images"):
        rs.record_sequence(tmp_path / "a.rrd", case.result, images[:4])
    with pytest.raises(BadInput, match="truth sidecars"):
        rs.record_sequence(tmp_path / "a.rrd", case.result, images, truths=[case.sim.frames[0].truth])
    with pytest.raises(BadInput, match="turns"):
        rs.record_sequence(tmp_path / "a.rrd", case.result, images, turns=[np.eye(3)])
    with pytest.raises(BadInput, match="does not exist"):
        rs.record_sequence(tmp_path / "no" / "a.rrd", case.result, images)
    keep = tmp_path / "keep.rrd"
    keep.write_bytes(b"precious")
    with pytest.raises(BadInput, match="exists; use --force"):
        rs.record_sequence(keep, case.result, images)
    assert keep.read_bytes() == b"precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.rrd"]  # nothing else left behind


# ============================================================================ the CLI

@pytest.mark.slow
def test_solve_sequence_record(paper, tmp_path, capsys, monkeypatch):
    case = paper[0]
    folder = tmp_path / "seq"
    folder.mkdir()
    save_sequence(case.sim, folder)
    out = tmp_path / "solved.rrd"
    assert main(["solve-sequence", str(folder), "--json", "--record", str(out)]) == 0
    o, err = capsys.readouterr()
    result = json.loads(o)  # stdout stays pure JSON; the "recorded" line goes to stderr
    assert result["status"] == "solved" and f"recorded {out}" in err and "5 frames" in err
    ents = read(out)
    frames = sorted(per_frame(ents["/camera/image"], "EncodedImage:blob"))
    assert frames == list(range(result["n_frames"]))
    k = result["frame"]
    M = np.array(last(ents["/camera"], "Transform3D:mat3x3")[k]).reshape(3, 3).T
    np.testing.assert_allclose(M, result["R"], atol=1e-6)  # the identified frame's estimated attitude
    tp = last(ents[f"/{rs.TRUE_POSTERIOR}"], "Scalars:scalars")
    np.testing.assert_allclose([tp[f][0] for f in sorted(tp)], [f["true_posterior"] for f in result["frames"]])
    assert "/truth/camera" in ents  # the sidecars' truth
    # bad recording paths: one line, exit 2, checked before anything is solved, nothing overwritten
    import skyview.solver.sequence

    def boom(*a, **k):
        raise AssertionError("solved before the recording path was checked")

    monkeypatch.setattr(skyview.solver.sequence, "solve_sequence", boom)
    before = out.read_bytes()
    for argv in (["solve-sequence", str(folder), "--record", str(out)],
                 ["solve-sequence", str(folder), "--record", str(tmp_path / "missing" / "x.rrd")],
                 ["solve-sequence", str(folder), "--record", str(tmp_path / "x.json")],
                 ["solve-sequence", str(folder), "--record", str(folder)]):
        code = main(argv)
        _, err = capsys.readouterr()
        assert code == 2 and one_line_error(err), (argv, err)
    assert out.read_bytes() == before
    assert "exists; use --force" in (main(["solve-sequence", str(folder), "--record", str(out)]) == 2
                                     and capsys.readouterr().err)
    monkeypatch.undo()
    assert main(["solve-sequence", str(folder), "--record", str(out), "--force", "--no-truth"]) == 0
    capsys.readouterr()
    ents = read(out)
    assert "/truth/camera" not in ents and "/camera" in ents


@pytest.mark.slow
def test_record_stochastic_command(tmp_path, capsys):
    out = tmp_path / "st.rrd"
    assert main(["record", "--method", "stochastic", "--seed", "0", str(out)]) == 0
    said = capsys.readouterr().out
    assert f"recorded {out}" in said and "5 frames" in said and "identified at frame 4" in said
    assert "10 arcsec" in said and "correct against truth" in said
    ents = read(out)
    assert sorted(per_frame(ents["/camera/image"], "EncodedImage:blob")) == [0, 1, 2, 3, 4]
    before = out.read_bytes()
    for argv in (["record", "--method", "stochastic", str(out)],  # exists
                 ["record", "--method", "stochastic", "--out", str(out)],
                 ["record", "--method", "stochastic", str(tmp_path / "missing" / "a.rrd")],
                 ["record", "--method", "stochastic", str(tmp_path / "a.png")],
                 ["record", "--method", "stochastic", "--scenario", "nope", str(tmp_path / "b.rrd")],
                 ["record", "--method", "stochastic", "--variant", "best", str(tmp_path / "b.rrd")],
                 ["record", "--method", "stochastic", str(tmp_path / "c.rrd"), "--out", str(tmp_path / "d.rrd")]):
        code = main(argv)
        _, err = capsys.readouterr()
        assert code == 2 and one_line_error(err), (argv, err)
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["st.rrd"]
    assert main(["record", "--method", "stochastic", "--variant", "improved", "--seed", "0", str(out), "--force"]) == 0
    assert "stochastic (improved)" in capsys.readouterr().out


def test_examples_write_the_sequence(tmp_path, monkeypatch, capsys):
    import skyview.identify

    monkeypatch.setattr(skyview.identify, "METHODS", {"stochastic": skyview.identify.METHODS["stochastic"]})
    assert main(["record", "--examples", "--out", str(tmp_path)]) == 0
    said = capsys.readouterr().out
    manifest = json.loads((tmp_path / "index.json").read_text())
    assert [e["file"] for e in manifest["files"]] == ["stochastic-udomkesmalee30.rrd"], said
    e = manifest["files"][0]
    assert e["outcome"] == "correct" and e["status"] == "solved" and e["frames"] == 5
    assert e["identified_frames"] and e["identified_frames"][-1] == 4 and e["noise_arcsec"] == 10
    assert e["seed"] == record_examples.EXAMPLE_SEED_START  # the first seed from 1 that the paper variant identifies
    ents = read(tmp_path / e["file"])
    assert ents["/steps/log"]["rows"] == e["steps"] and e["bytes"] == (tmp_path / e["file"]).stat().st_size
    tp = last(ents[f"/{rs.TRUE_POSTERIOR}"], "Scalars:scalars")
    np.testing.assert_allclose([tp[k][0] for k in sorted(tp)], e["true_posterior"], atol=1e-4)


def test_committed_sequence_example():
    manifest = json.loads((REPO / "recordings" / "index.json").read_text())
    entry = next(e for e in manifest["files"] if e["file"] == EXAMPLE.name)
    assert EXAMPLE.stat().st_size == entry["bytes"] < 2_000_000
    ents = read(EXAMPLE)
    frames = sorted(per_frame(ents["/camera/image"], "EncodedImage:blob"))
    assert frames == list(range(entry["frames"])) == [0, 1, 2, 3, 4]
    assert ents["/steps/log"]["rows"] == entry["steps"]
    tp = last(ents[f"/{rs.TRUE_POSTERIOR}"], "Scalars:scalars")
    np.testing.assert_allclose([tp[k][0] for k in sorted(tp)], entry["true_posterior"], atol=1e-4)
    assert tp[4][0] > 0.95
    poses = last(ents["/camera"], "Transform3D:mat3x3")
    true_poses = last(ents["/truth/camera"], "Transform3D:mat3x3")
    for k in entry["identified_frames"]:  # an estimated attitude, within arcminutes of the truth
        M, T = (np.array(p[k]).reshape(3, 3).T for p in (poses, true_poses))
        assert np.degrees(np.arccos(np.clip(M[2] @ T[2], -1, 1))) * 3600 < 60


# ============================================================================ the viewer

@needs_lavapipe
def test_viewer_opens_the_sequence_example(viewer, tmp_path):  # noqa: F811 (the fixture imported above)
    from PIL import Image

    state = _open(viewer, EXAMPLE)
    views = {v.name: v for v in state.views}
    assert {"sky", "image", "posterior over frames", "stars above 1/N", "step log", "result"} <= set(views)
    assert views["posterior over frames"].origin == f"/{rs.POSTERIOR}"
    assert all(not v.reports for v in state.views), [(v.name, v.reports) for v in state.views]
    active = next(r for r in state.recordings if r.store_id == state.active_recording)
    tl = {t.name: (t.start, t.end) for t in active.timelines}
    manifest = json.loads((REPO / "recordings" / "index.json").read_text())
    entry = next(e for e in manifest["files"] if e["file"] == EXAMPLE.name)
    assert tl["frame"] == (0, 4) and tl["step"] == (0, entry["steps"] - 1)

    def shot(frame):
        viewer.set_time("frame", sequence=frame, play_state="paused")
        return _shot_frame(viewer)

    first, last_ = shot(0), shot(4)
    Image.fromarray(last_.astype(np.uint8)).save(tmp_path / "frame4.png")
    h, w, _ = first.shape
    sky = last_[int(0.1 * h):int(0.9 * h), :int(0.55 * w)]
    assert sky.std() > 10 and (sky.max(axis=-1) > 120).mean() > 0.002, "the 3D sky looks blank"
    assert (np.abs(first - last_).sum(-1) > 30).mean() > 1e-3  # another frame, another picture


def _shot_frame(client) -> np.ndarray:
    import io
    import time

    from PIL import Image

    time.sleep(0.5)
    return np.asarray(Image.open(io.BytesIO(client.take_screenshot())).convert("RGB")).astype(int)
