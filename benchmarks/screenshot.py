"""Screenshot of a web page (the dashboard's packings page) in headless Chromium.

Drives Debian's ``chromium`` over the DevTools protocol: opens the page, waits
(a Bokeh page draws once its websocket delivers the document), and saves a PNG;
prints the page's text, shadow DOM included (Bokeh draws into shadow roots), and
any error the page's scripts raised.  The README's screenshot is made with::

    python -m benchmarks screenshot http://127.0.0.1:8787/packings -o docs/images/dashboard.png
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import shutil
import signal
import subprocess
import tempfile
import threading
import time
import urllib.request

#: the text of a page, through every shadow root (Bokeh's widgets live in them)
_TEXT = """(() => { const out = []; const walk = (n) => {
  if (n.nodeType === 3) { out.push(n.textContent); return; }
  if (n.nodeName === 'STYLE' || n.nodeName === 'SCRIPT') return;
  if (n.shadowRoot) walk(n.shadowRoot);
  for (const c of n.childNodes) walk(c); };
  walk(document.body); return out.join(' ').replace(/\\s+/g, ' '); })()"""


def add_arguments(p) -> None:
    p.add_argument("url")
    p.add_argument("-o", "--output", default="dashboard.png")
    p.add_argument("--wait", type=float, default=5.0, help="seconds to let the page draw")
    p.add_argument("--size", default="1000x1100", help="window WIDTHxHEIGHT")
    p.add_argument("--json", action="store_true")


def render(url: str, wait: float = 5.0, width: int = 1000, height: int = 1100, until: str | None = None) -> dict:
    """{"text": the page's text, "png": bytes, "errors": [...]} after ``wait`` seconds; with ``until``, as soon
    as the page's text holds it (read every 0.2 s), ``wait`` seconds at most."""
    return asyncio.run(_render(url, wait, width, height, until))


async def _render(url: str, wait: float, width: int, height: int, until: str | None = None) -> dict:
    from tornado.websocket import websocket_connect

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise RuntimeError("no chromium on PATH (Debian: apt-get install chromium)")
    profile = tempfile.TemporaryDirectory(ignore_cleanup_errors=True)
    proc = subprocess.Popen(
        [
            chromium,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            "--remote-debugging-port=0",
            f"--user-data-dir={profile.name}",
            "about:blank",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        port = _devtools_port(proc)
        deadline = time.monotonic() + 30
        while True:
            try:
                tabs = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=2).read())
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.1)
        ws = await websocket_connect(
            next(t["webSocketDebuggerUrl"] for t in tabs if t["type"] == "page"), max_message_size=1 << 28
        )
        errors: list[str] = []
        ids = iter(range(1, 1 << 30))

        async def call(method: str, **params) -> dict:
            mid = next(ids)
            await ws.write_message(json.dumps({"id": mid, "method": method, "params": params}))
            while True:
                m = json.loads(await ws.read_message())
                if m.get("method") == "Runtime.exceptionThrown":
                    errors.append(m["params"]["exceptionDetails"].get("text", "exception"))
                if m.get("id") == mid:
                    return m.get("result", {})

        await call("Runtime.enable")
        await call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)
        await call("Page.navigate", url=url)
        end = time.monotonic() + wait
        while True:
            if until is None:
                await asyncio.sleep(wait)
            text = (await call("Runtime.evaluate", expression=_TEXT, returnByValue=True))["result"].get("value", "")
            if until is None or until in text or time.monotonic() > end:
                break
            await asyncio.sleep(0.2)
        png = base64.b64decode((await call("Page.captureScreenshot", format="png"))["data"])
        ws.close()
        return {"text": text, "png": png, "errors": errors}
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # chromium and its helper processes
        proc.wait()
        profile.cleanup()


def _devtools_port(proc) -> int:
    """Chromium says on standard error where its DevTools listen (port 0: it chose one)."""
    for line in proc.stderr:
        if "DevTools listening on ws://" in line:
            # the rest is read and dropped, so that chromium never blocks on a full pipe
            threading.Thread(target=proc.stderr.read, daemon=True).start()
            return int(line.split("ws://", 1)[1].split("/", 1)[0].rsplit(":", 1)[1])
    raise RuntimeError("chromium did not start its DevTools server")


def run(args) -> int:
    width, height = (int(v) for v in args.size.lower().split("x"))
    out = render(args.url, args.wait, width, height)
    with open(args.output, "wb") as f:
        f.write(out["png"])
    if args.json:
        print(json.dumps({"text": out["text"], "errors": out["errors"], "output": args.output}))
    else:
        print(out["text"])
        for e in out["errors"]:
            print("page error:", e)
    return 1 if out["errors"] else 0
