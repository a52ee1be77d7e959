"""A browser tab as the viewer's server sees it: viser's websocket protocol, spoken from Python.

What the load test (tests/test_viewer_load.py, benchmarks/viewer_load.py) needs of a tab, without a browser:
connect (the subprotocol `viser-v<version>` and a first camera message: viser creates the client, and
skyview its `Session`, on that message), read the panel the server builds (its GUI components and their
updates), upload a file through the panel's upload button (FileTransferStartUpload + parts, as the
frontend sends them), click a button, and receive the files the server sends back (FileTransferStartDownload
+ parts: the "Download the result (JSON)" button's answer).

Wire format (viser 1.1.1, `viser/infra/_infra.py`): client -> server, one msgpack dict per frame with its
message class's name under "type"; server -> client, a window of messages per frame: 8 bytes
decompressed size, 8 bytes compressed size, zstd-compressed msgpack {"messages": [...], ...}, then the
binary buffers the messages point at (not needed here: textures and point clouds).
"""

from __future__ import annotations

import asyncio
import time
import uuid as uuidlib
from dataclasses import dataclass, field

import msgspec
import viser
import websockets
import zstandard

PART_BYTES = 512 * 1024  # an upload is sent in parts of this size, as the frontend splits it


@dataclass
class Component:
    """One GUI component of the tab's panel as the server described it (its props updated as they change)."""

    kind: str  # the message's class, e.g. "GuiMarkdownMessage"
    props: dict
    value: object = None


@dataclass
class Tab:
    """One connected tab. Use `await Tab.open(port)`; every method is a coroutine on the caller's loop."""

    ws: object
    gui: dict[str, Component] = field(default_factory=dict)
    scene: dict[str, dict] = field(default_factory=dict)  # scene node name -> {"kind", "props", "wxyz", "position"}
    downloads: list[tuple[str, bytes]] = field(default_factory=list)
    changed: asyncio.Event = field(default_factory=asyncio.Event)
    closed: bool = False
    _incoming: dict[str, dict] = field(default_factory=dict)
    _reader: asyncio.Task | None = None

    @classmethod
    async def open(cls, port: int, host: str = "127.0.0.1") -> "Tab":
        ws = await websockets.connect(f"ws://{host}:{port}", subprotocols=[f"viser-v{viser.__version__}"],
                                      max_size=None, ping_interval=None)
        tab = cls(ws)
        tab._reader = asyncio.get_running_loop().create_task(tab._read())
        # the first camera message makes the client (and skyview's session for it)
        await tab.send("ViewerCameraMessage", wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, -3.0), fov=1.0,
                       near=0.01, far=100.0, image_height=1000, image_width=1600, look_at=(0.0, 0.0, 0.0),
                       up_direction=(0.0, -1.0, 0.0))
        return tab

    async def send(self, kind: str, **fields) -> None:
        await self.ws.send(msgspec.msgpack.encode({"type": kind, **fields}))

    async def close(self) -> None:
        self.closed = True
        await self.ws.close()
        if self._reader is not None:
            self._reader.cancel()
            await asyncio.gather(self._reader, return_exceptions=True)

    # ------------------------------------------------------------------ reading the server
    async def _read(self) -> None:
        unzstd = zstandard.ZstdDecompressor()
        try:
            async for raw in self.ws:
                n, c = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
                window = msgspec.msgpack.decode(unzstd.decompress(raw[16:16 + c], max_output_size=n))
                buffers, at = [], 16 + c
                for length in window.get("binaryBufferLengths", ()):
                    at += (8 - at % 8) % 8  # each buffer 8-byte aligned after the compressed metadata
                    buffers.append(raw[at:at + length])
                    at += length
                for m in window["messages"]:
                    self._take(_with_arrays(m, buffers))
                self.changed.set()
        except websockets.ConnectionClosed:
            pass
        finally:
            self.closed = True
            self.changed.set()

    def _take(self, m: dict) -> None:
        kind = m["type"]
        if kind.startswith("Gui") and "props" in m and "uuid" in m:
            self.gui[m["uuid"]] = Component(kind, dict(m["props"]), m.get("value"))
        elif kind == "GuiUpdateMessage" and m["uuid"] in self.gui:
            c = self.gui[m["uuid"]]
            for key, v in m["updates"].items():
                if key == "value":
                    c.value = v
                else:
                    c.props[key] = v
        elif kind == "GuiRemoveMessage":
            self.gui.pop(m["uuid"], None)
        elif "name" in m and kind in ("SetOrientationMessage", "SetPositionMessage"):
            node = self.scene.setdefault(m["name"], {"kind": None, "props": {}})
            node["wxyz" if kind == "SetOrientationMessage" else "position"] = m.get("wxyz", m.get("position"))
        elif kind == "SceneNodeUpdateMessage" and m["name"] in self.scene:
            self.scene[m["name"]]["props"].update(m["updates"])
        elif kind == "RemoveSceneNodeMessage":
            self.scene.pop(m["name"], None)
        elif "name" in m and "props" in m:  # a scene node made (or made again)
            self.scene[m["name"]] = {"kind": kind, "props": dict(m["props"]), "wxyz": (1.0, 0.0, 0.0, 0.0),
                                     "position": (0.0, 0.0, 0.0)}
        elif kind == "FileTransferStartDownload":
            self._incoming[m["transfer_uuid"]] = {"name": m["filename"], "count": m["part_count"], "parts": {}}
            self._finish_download(m["transfer_uuid"])
        elif kind == "FileTransferPart" and m["transfer_uuid"] in self._incoming:
            self._incoming[m["transfer_uuid"]]["parts"][m["part_index"]] = m["content"]
            self._finish_download(m["transfer_uuid"])

    def _finish_download(self, transfer: str) -> None:
        d = self._incoming[transfer]
        if len(d["parts"]) == d["count"]:
            del self._incoming[transfer]
            self.downloads.append((d["name"], b"".join(d["parts"][i] for i in range(d["count"]))))

    # ------------------------------------------------------------------ the panel
    def find(self, kind: str, text: str) -> str | None:
        """The uuid of the first component of this kind whose label (or markdown) starts with `text`."""
        for key, c in sorted(self.gui.items(), key=lambda kv: kv[1].props.get("order", 0)):
            if c.kind == kind and str(c.props.get("label", c.props.get("_markdown", ""))).startswith(text):
                return key
        return None

    def markdown(self, key: str) -> str:
        return str(self.gui[key].props.get("_markdown", ""))

    async def wait_until(self, ready, timeout: float) -> object:
        """Wait until `ready()` returns something true (checked after every window the server sends)."""
        deadline = time.monotonic() + timeout
        while True:
            got = ready()
            if got:
                return got
            if self.closed:
                raise ConnectionError("the server closed the tab")
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("the tab waited too long")
            self.changed.clear()
            try:
                await asyncio.wait_for(self.changed.wait(), min(left, 0.5))
            except asyncio.TimeoutError:
                pass

    async def wait_for_panel(self, timeout: float = 60.0) -> str:
        """The panel is up and takes uploads (its upload button enabled, as a browser's user can click it
        only then): the uuid of its upload button."""
        def ready():
            key = self.find("GuiUploadButtonMessage", "")
            return key if key is not None and not self.gui[key].props.get("disabled") else None

        return await self.wait_until(ready, timeout)

    async def upload(self, button: str, name: str, content: bytes, mime: str = "image/png") -> None:
        """Send a file through an upload button, in parts, as the frontend does."""
        transfer = str(uuidlib.uuid4())
        parts = [content[i:i + PART_BYTES] for i in range(0, len(content), PART_BYTES)]
        await self.send("FileTransferStartUpload", source_component_uuid=button, transfer_uuid=transfer,
                        filename=name, mime_type=mime, part_count=len(parts), size_bytes=len(content))
        for i, part in enumerate(parts):
            await self.send("FileTransferPart", source_component_uuid=button, transfer_uuid=transfer,
                            part_index=i, content=part)

    async def click(self, button: str) -> None:
        await self.send("GuiUpdateMessage", uuid=button, updates={"value": True})


BUSY = ("⏳", "waiting for a free core", "starting…")  # skyview's status line while a job runs or waits


async def skyview_panel(tab: Tab) -> dict[str, str]:
    """The uuids of skyview's panel components the load test uses: upload, status, error, download."""
    upload = await tab.wait_for_panel()
    # the panel arrives component by component: this button comes after the status and error lines
    download = await tab.wait_until(lambda: tab.find("GuiButtonMessage", "Download the result (JSON)"), 60)
    markdowns = sorted((c.props["order"], k) for k, c in tab.gui.items() if c.kind == "GuiMarkdownMessage"
                       and c.props["order"] > tab.gui[upload].props["order"])
    # the status line is the first markdown after the upload button, the error line the next one
    return {"upload": upload, "status": markdowns[0][1], "error": markdowns[1][1], "download": download}


def _error(tab: Tab, panel: dict) -> str:
    c = tab.gui[panel["error"]]
    return str(c.props.get("_markdown", "")) if c.props.get("visible") else ""


async def wait_for_idle(tab: Tab, timeout: float = 300.0, unlike: str | None = None) -> str:
    """The tab's status line once no job runs or waits (and, given `unlike`, once it says something else)."""
    panel = await skyview_panel(tab)

    def idle():
        if _error(tab, panel):
            raise RuntimeError(_error(tab, panel))
        text = tab.markdown(panel["status"])
        return text if text != unlike and not text.startswith(BUSY) else None

    return await tab.wait_until(idle, timeout)


def _with_arrays(value, buffers: list[bytes]):
    """A message with viser's binary placeholders ({"__binary_index": i, "dtype": ...}) replaced by 1-D numpy
    arrays over the window's buffers (a point cloud's points come as (3N,): reshape where the shape is known)."""
    import numpy as np

    if isinstance(value, dict):
        if "__binary_index" in value and "dtype" in value:
            return np.frombuffer(buffers[value["__binary_index"]], dtype=np.dtype(value["dtype"]))
        return {k: _with_arrays(v, buffers) for k, v in value.items()}
    if isinstance(value, list):
        return [_with_arrays(v, buffers) for v in value]
    return value


async def solve_by_upload(tab: Tab, name: str, content: bytes, timeout: float = 300.0) -> dict:
    """skyview's viewer, as a user drives it: upload a photograph with the panel's upload button, wait for
    the status line to show a finished job, and press "Download the result (JSON)" until the answer is
    this photograph's (`image` == name). Returns the solution's JSON (the shape `skyview solve --json` prints)."""
    import json

    panel = await skyview_panel(tab)
    seen = tab.markdown(panel["status"])
    await tab.upload(panel["upload"], name, content)
    deadline = time.monotonic() + timeout
    while True:
        seen = await wait_for_idle(tab, deadline - time.monotonic(), unlike=seen)
        n = len(tab.downloads)
        await tab.click(panel["download"])
        await tab.wait_until(lambda: len(tab.downloads) > n or _error(tab, panel), deadline - time.monotonic())
        if _error(tab, panel):
            raise RuntimeError(f"{name}: {_error(tab, panel)}")
        answer = json.loads(tab.downloads[-1][1])
        if answer.get("image") == name:
            return answer
