"""A viewer for a class (issue 28, item 4): every tab's solve takes its turn on a bounded number of slots,
first come first served, and says its place; a closed tab's waiting request leaves the queue; thirty tabs
uploading thirty different photographs at once each get their own answer (no cross-talk).
The tabs speak viser's websocket protocol (tests/viser_protocol.py), as a browser does. The figures (time to
open a tab under load, memory over many uploads) come from `benchmarks/viewer_load.py`, not from these tests."""

from __future__ import annotations

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


def _sep_arcsec(ra1, dec1, ra2, dec2) -> float:
    r1, d1, r2, d2 = map(math.radians, (ra1, dec1, ra2, dec2))
    c = math.sin(d1) * math.sin(d2) + math.cos(d1) * math.cos(d2) * math.cos(r1 - r2)
    return math.degrees(math.acos(min(1.0, c))) * 3600


@pytest.mark.slow
def test_thirty_tabs_uploading_at_once_over_the_websocket_each_get_their_own_answer():
    """Thirty tabs speak viser's websocket protocol to one `skyview view` server (tests/viser_protocol.py: what
    a browser sends and reads, without the rendering): each uploads its own photograph through the panel's
    upload button at the same moment, and reads its answer back through "Download the result (JSON)".
    Three more tabs upload and close at once: their requests leave the queue, their sessions are released; so
    are those of five tabs closed while the server was still building their panel."""
    import asyncio

    from viser_protocol import Tab, solve_by_upload

    from skyview.viewer.app import ViewerApp

    photos = _variants()[:30]
    app = ViewerApp(port=0)

    async def drive():
        tabs = await asyncio.gather(*(Tab.open(app.port) for _ in range(len(photos) + 3)))
        await asyncio.gather(*(t.wait_for_panel() for t in tabs))
        for _ in range(600):  # the panel reaches the tab while its session is still being registered
            if len(app.sessions) == len(tabs):
                break
            await asyncio.sleep(0.05)
        assert len(app.sessions) == len(tabs)  # one session per tab
        for s in app.sessions.values():
            assert s.wait_idle(120)
        served = app.solvers.queue.served
        pngs = [cv2.imencode(".png", img)[1].tobytes() for _, img, *_ in photos]
        solving = asyncio.gather(*(solve_by_upload(t, name + ".png", png)
                                   for t, (name, *_), png in zip(tabs, photos, pngs)))
        for t in tabs[len(photos):]:  # three tabs closed while their uploads wait for a turn
            await t.upload(await t.wait_for_panel(), "x.png", pngs[0])
            await t.close()
        for t in await asyncio.gather(*(Tab.open(app.port) for _ in range(5))):
            await t.close()  # five tabs closed before their panel arrived: their sessions are released too
        answers = await solving
        for t in tabs[:len(photos)]:
            await t.close()
        return served, answers

    try:
        served, answers = asyncio.run(drive())
        for answer, (name, _img, ra, dec, fov) in zip(answers, photos):
            assert answer["solved"] and answer["image"] == name + ".png", (name, answer.get("reason"))
            assert _sep_arcsec(answer["ra_deg"], answer["dec_deg"], ra, dec) < 120, name  # its own photograph
            assert answer["fov_deg"] == pytest.approx(fov, rel=0.01), name
            assert np.allclose(np.asarray(answer["R"]) @ np.asarray(answer["R"]).T, np.eye(3), atol=1e-9)
        # every open tab's upload took a turn; a closed tab's request took at most the turn it had begun
        q = app.solvers.queue
        assert served + len(photos) <= q.served <= served + len(photos) + 3 + 5
        deadline = time.monotonic() + 30
        while (app.sessions or q.waiting() or q.running) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not app.sessions and q.waiting() == 0 and q.running == 0  # every closed tab's session released
    finally:
        app.stop()


@pytest.mark.slow
def test_an_idle_tab_is_sent_nothing_after_its_answer():
    """A solved photograph on screen and nobody touching it: the server sends the tab no message at all (viser's
    client renders on demand, so a tab that is sent nothing stays idle)."""
    import asyncio

    from viser_protocol import Tab, solve_by_upload

    from skyview.viewer.app import ViewerApp

    name, img, *_ = _variants()[0]
    app = ViewerApp(port=0)

    async def drive():
        tab = await Tab.open(app.port)
        answer = await solve_by_upload(tab, name + ".png", cv2.imencode(".png", img)[1].tobytes())
        await asyncio.sleep(1.0)  # the answer's last windows
        seen = []
        take = tab._take
        tab._take = lambda m: (seen.append(m["type"]), take(m))
        await asyncio.sleep(4.0)
        await tab.close()
        return answer, seen

    try:
        answer, seen = asyncio.run(drive())
        assert answer["solved"]
        assert seen == []
    finally:
        app.stop()
