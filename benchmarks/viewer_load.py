"""The viewer under a class's load: N tabs uploading at once, round after round, to one `skyview view`.

    SKYVIEW_CACHE=/tmp/svcache .venv/bin/python benchmarks/viewer_load.py --tabs 30 --rounds 34

The server is a `skyview view` process of its own, as a classroom runs it (`--host 0.0.0.0` there; here
127.0.0.1). Each tab speaks viser's websocket protocol (tests/viser_protocol.py): the messages a browser
sends and reads, without the rendering. Every round, every tab uploads a photograph through the panel's
upload button at once (the eight real ones as they are, their centre halves, and turned a quarter and a
half turn: 32 known answers, tests/test_viewer_load.py) and reads its answer back through "Download the
result (JSON)"; meanwhile one more tab opens (the time until its panel's upload button arrives), and
`--closing` tabs upload and close at once (their requests must leave the queue, their sessions the server).
The script reports per round the time until every tab has its answer, each tab's time from upload to
answer (median, max), the new tab's time to its panel, how many answers were wrong (not solved, or a
boresight more than 120" from its own photograph's), and the server's resident memory after the round.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith("VmRSS")) / 1024


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_server(port: int, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    """Until the server answers an HTTP request for its page (as a browser's first request)."""
    import urllib.request

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"skyview view exited with {proc.returncode}")
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5):
                return
        except OSError:
            time.sleep(0.2)
    raise SystemExit("skyview view did not start")


async def run(a, port: int, pid: int) -> int:
    from test_viewer_load import _sep_arcsec, _variants
    from viser_protocol import Tab, solve_by_upload, wait_for_idle

    photos = [(name + ".png", cv2.imencode(".png", img)[1].tobytes(), ra, dec) for name, img, ra, dec, _ in _variants()]
    t0 = time.perf_counter()
    tabs = await asyncio.gather(*(Tab.open(port) for _ in range(a.tabs)))
    await asyncio.gather(*(wait_for_idle(t) for t in tabs))  # each tab's first scene solved and drawn
    print(f"{a.tabs} tabs open in {time.perf_counter() - t0:.1f} s; server RSS {rss_mb(pid):.0f} MB; "
          f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}", flush=True)
    print("| round | uploads | all answered (s) | upload to answer median / max (s) | a new tab's panel (s) | wrong "
          "| server RSS (MB) |")
    print("|---|---|---|---|---|---|---|")
    uploads = wrong_total = 0
    worst_open = 0.0
    for r in range(a.rounds):
        times = [0.0] * a.tabs

        async def one(k: int) -> bool:
            name, png, ra, dec = photos[(k + r) % len(photos)]
            t = time.perf_counter()
            answer = await solve_by_upload(tabs[k], name, png, timeout=600)
            times[k] = time.perf_counter() - t
            return bool(answer["solved"]) and _sep_arcsec(answer["ra_deg"], answer["dec_deg"], ra, dec) < 120

        t_round = time.perf_counter()
        solving = asyncio.gather(*(one(k) for k in range(a.tabs)))
        await asyncio.sleep(0.05)  # the uploads are on their way: the new tab and the closing ones arrive under load
        closing = await asyncio.gather(*(Tab.open(port) for _ in range(a.closing)))
        for t in closing:
            await t.upload(await t.wait_for_panel(), photos[0][0], photos[0][1])
            await t.close()
        opened = float("nan")
        if a.new_tab:
            t_new = time.perf_counter()
            extra = await Tab.open(port)
            await extra.wait_for_panel()
            opened = time.perf_counter() - t_new
            await extra.close()
        good = await solving
        wrong = len(good) - sum(good)
        uploads += a.tabs + a.closing
        wrong_total += wrong
        worst_open = max(worst_open, opened) if a.new_tab else worst_open
        await asyncio.sleep(1.0)  # closed tabs' sessions are released a moment after they leave
        print(f"| {r + 1} | {uploads} | {time.perf_counter() - t_round - 1.0:.1f} | {np.median(times):.2f} / "
              f"{max(times):.2f} | {opened:.2f} | {wrong} | {rss_mb(pid):.0f} |", flush=True)
    for t in tabs:
        await t.close()
    print(f"{uploads} uploads, {wrong_total} wrong" + (f"; a new tab's panel in at most {worst_open:.2f} s"
                                                        if a.new_tab else ""))
    return 1 if wrong_total else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tabs", type=int, default=30)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--closing", type=int, default=3, help="tabs that upload and close at once, each round")
    ap.add_argument("--no-new-tab", dest="new_tab", action="store_false",
                    help="no extra tab opens during a round (e.g. --tabs 1 --closing 0: one user's round trip)")
    a = ap.parse_args(argv)
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "skyview", "view", "--port", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        wait_for_server(port, proc)
        return asyncio.run(run(a, port, proc.pid))
    finally:
        proc.terminate()
        try:
            _, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
        if err.strip():
            print("server stderr:\n" + err[-3000:], file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
