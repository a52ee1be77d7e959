"""The viewer under a class's load: N tabs uploading at once, round after round, on this machine.

    SKYVIEW_CACHE=/tmp/svcache .venv/bin/python benchmarks/viewer_load.py --tabs 30 --rounds 10

Each tab is a viewer `Session` with its own scene and panel (a viser server each, as a browser tab has its
own client) sharing one `Solvers` and its `SolveQueue`, as `skyview view` shares them between tabs. Every
round, every tab uploads a photograph at once (the eight real ones as they are, their centre halves, and
turned a quarter and a half turn: 32 known answers, tests/test_viewer_load.py); the script reports per
round the time until every tab has drawn its answer, each tab's time from upload to answer (median, max),
the time to open one more tab while they solve, how many answers were wrong (boresight more than 120"
from its own photograph's), and the process's resident memory after each round.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import io
import math
import resource
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))


def rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * resource.getpagesize() / 2 ** 20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tabs", type=int, default=30)
    ap.add_argument("--rounds", type=int, default=5)
    a = ap.parse_args(argv)
    import viser

    from skyview.core.attitude import radec_roll_from_R
    from skyview.viewer.run import Solvers
    from skyview.viewer.session import Session
    from test_viewer_load import _variants

    photos = _variants()
    solvers = Solvers()
    servers = []

    def tab():
        with contextlib.redirect_stdout(io.StringIO()):
            servers.append(viser.ViserServer(host="127.0.0.1", port=0, verbose=False))
        return Session(servers[-1], solvers)

    t0 = time.perf_counter()
    tabs = [tab() for _ in range(a.tabs)]
    for s in tabs:
        s.wait_idle(300)
    print(f"{a.tabs} tabs open in {time.perf_counter() - t0:.1f} s; {solvers.queue.slots} solve slots; "
          f"RSS {rss_mb():.0f} MB", flush=True)
    print("| round | all answered (s) | upload to answer median / max (s) | one more tab opens in (s) | wrong | RSS (MB) |")
    print("|---|---|---|---|---|---|")
    encoded = [(name, cv2.imencode(".png", img)[1].tobytes(), ra, dec) for name, img, ra, dec, _ in photos]
    for r in range(a.rounds):
        done = [None] * a.tabs
        t_up = time.perf_counter()
        for k, s in enumerate(tabs):
            name, png, *_ = encoded[(k + r) % len(encoded)]
            s.receive_upload(f"{name}", png)

        def wait(k):
            tabs[k].wait_idle(600)
            done[k] = time.perf_counter() - t_up

        waiters = [threading.Thread(target=wait, args=(k,)) for k in range(a.tabs)]
        for w in waiters:
            w.start()
        t_new = time.perf_counter()
        extra = tab()  # a new tab while the others solve: its panel is built before it waits for a turn
        opened = time.perf_counter() - t_new
        for w in waiters:
            w.join()
        extra.wait_idle(600)
        extra.close()  # the tab closed again, its server with it (as a browser tab's client goes)
        with contextlib.redirect_stdout(io.StringIO()):
            servers.pop().stop()
        del extra
        gc.collect()
        wrong = 0
        for k, s in enumerate(tabs):
            _, _, ra, dec = encoded[(k + r) % len(encoded)]
            res = s.run.result
            if not res.solved:
                wrong += 1
                continue
            ra_s, dec_s, _ = (math.degrees(x) for x in radec_roll_from_R(res.R))
            c = (math.sin(math.radians(dec_s)) * math.sin(math.radians(dec)) + math.cos(math.radians(dec_s))
                 * math.cos(math.radians(dec)) * math.cos(math.radians(ra_s - ra)))
            wrong += math.degrees(math.acos(min(1.0, c))) * 3600 > 120
        print(f"| {r + 1} | {max(done):.1f} | {np.median(done):.1f} / {max(done):.1f} | {opened:.2f} | {wrong} | "
              f"{rss_mb():.0f} |", flush=True)
    for s in tabs:
        s.close()
    with contextlib.redirect_stdout(io.StringIO()):
        for server in servers:
            server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
