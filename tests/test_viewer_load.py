"""A viewer for a class (issue 28, item 4): every tab's solve takes its turn on a bounded number of slots,
first come first served, and says its place; a closed tab's waiting request leaves the queue; thirty tabs
uploading thirty different photographs at once each get their own answer (no cross-talk).
The figures (time to open a tab under load, memory over many uploads) come from
`benchmarks/viewer_load.py`, not from these tests."""

from __future__ import annotations

import contextlib
import io
import json
import math
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from skyview.viewer.solve_queue import SolveQueue, Superseded

REAL = Path(__file__).parent / "data" / "real-images"
REFERENCE = json.loads((REAL / "reference.json").read_text())


def test_turns_are_first_come_first_served_on_the_slots():
    q = SolveQueue(slots=1)
    order, started = [], threading.Event()
    places: dict[int, list[str]] = {k: [] for k in range(4)}

    def hold():
        with q.turn():
            started.set()
            time.sleep(0.3)

    def ask(k):
        with q.turn(places[k].append):
            order.append(k)

    t0 = threading.Thread(target=hold)
    t0.start()
    started.wait(5)
    threads = []
    for k in range(4):  # asked in this order while the slot is held
        threads.append(threading.Thread(target=ask, args=(k,)))
        threads[-1].start()
        while q.waiting() < k + 1:
            time.sleep(0.005)
    for t in [t0, *threads]:
        t.join(10)
    assert order == [0, 1, 2, 3] and q.served == 5
    assert places[3][0] == "waiting for a free core: 3 ahead of you" and places[0] == ["waiting for a free core: next"]


def test_a_stale_request_leaves_the_queue_without_its_turn():
    q = SolveQueue(slots=1)
    wanted = threading.Event()
    wanted.set()
    got = []
    started = threading.Event()

    def hold():
        with q.turn():
            started.set()
            time.sleep(0.4)

    def ask():
        try:
            with q.turn(stale=lambda: not wanted.is_set()):
                got.append("ran")
        except Superseded:
            got.append("left")

    h = threading.Thread(target=hold)
    h.start()
    started.wait(5)
    t = threading.Thread(target=ask)
    t.start()
    while q.waiting() < 1:
        time.sleep(0.005)
    wanted.clear()  # the tab was closed while it waited
    t.join(5)
    assert got == ["left"] and q.waiting() == 0
    h.join(5)
    assert q.served == 1


def _variants() -> list[tuple[str, np.ndarray, float, float, float]]:
    """Thirty-two photographs with known answers: the eight real ones as they are, their centre halves (half
    the FOV), and turned a quarter and a half turn (the boresight stays; a quarter turn swaps the FOVs)."""
    out = []
    for name in sorted(REFERENCE):
        ref = REFERENCE[name]
        img = cv2.imread(str(REAL / name), cv2.IMREAD_UNCHANGED)
        h, w = img.shape
        fov_v = math.degrees(2 * math.atan(math.tan(math.radians(ref["fov_deg"]) / 2) * h / w))
        out.append((name, img, ref["ra_deg"], ref["dec_deg"], ref["fov_deg"]))
        out.append(("half-" + name, np.ascontiguousarray(img[h // 4: h // 4 + h // 2, w // 4: w // 4 + w // 2]),
                    ref["ra_deg"], ref["dec_deg"], ref["fov_deg"] / 2))
        out.append(("quarter-" + name, np.ascontiguousarray(cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)),
                    ref["ra_deg"], ref["dec_deg"], fov_v))
        out.append(("half-turn-" + name, np.ascontiguousarray(cv2.rotate(img, cv2.ROTATE_180)),
                    ref["ra_deg"], ref["dec_deg"], ref["fov_deg"]))
    return out


@pytest.mark.slow
def test_thirty_tabs_uploading_at_once_each_get_their_own_answer():
    import viser

    from skyview.core.attitude import radec_roll_from_R
    from skyview.viewer.run import Solvers
    from skyview.viewer.session import Session

    # each tab's scene and panel its own (a viser server each, as a browser tab has its own client); the
    # solvers and their queue shared, as in `skyview view`
    solvers = Solvers()
    photos = _variants()[:30]
    servers = []

    def tab():
        with contextlib.redirect_stdout(io.StringIO()):
            servers.append(viser.ViserServer(host="127.0.0.1", port=0, verbose=False))
        return Session(servers[-1], solvers)

    sessions = [tab() for _ in photos]
    closing = [tab() for _ in range(3)]  # three more, closed mid-queue
    try:
        for s in sessions + closing:
            assert s.wait_idle(120)
        served = solvers.queue.served
        for s, (name, img, *_rest) in zip(sessions, photos):
            s.receive_upload(name + ".png", cv2.imencode(".png", img)[1].tobytes())
        for s in closing:
            s.receive_upload("x.png", cv2.imencode(".png", photos[0][1])[1].tobytes())
            s.close()
        for s in sessions:
            assert s.wait_idle(300), "a tab never finished"
        for s, (name, _img, ra, dec, fov) in zip(sessions, photos):
            r = s.run.result
            assert s.error == "" and r.solved, (name, s.error, r.reason)
            assert s.run.source.name.startswith(name)  # its own photograph
            a, d, _ = (math.degrees(x) for x in radec_roll_from_R(r.R))
            sep = math.degrees(math.acos(min(1.0, math.sin(math.radians(d)) * math.sin(math.radians(dec)) + math.cos(
                math.radians(d)) * math.cos(math.radians(dec)) * math.cos(math.radians(a - ra)))))
            assert sep * 3600 < 120, (name, sep * 3600)
            assert r.camera.fov_deg == pytest.approx(fov, rel=0.01), name
        # every open tab's upload took a turn; the closed tabs' requests took at most the turns they had begun
        assert served + len(sessions) <= solvers.queue.served <= served + len(sessions) + len(closing)
        assert solvers.queue.waiting() == 0 and solvers.queue.running == 0
    finally:
        for s in sessions:
            s.close()
        with contextlib.redirect_stdout(io.StringIO()):
            for server in servers:
                server.stop()
