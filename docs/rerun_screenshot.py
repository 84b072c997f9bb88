"""Screenshot of the Rerun web viewer showing an .rrd (how ``docs/rerun_view.png`` was made).

    python docs/rerun_screenshot.py RUN.rrd docs/rerun_view.png [--wait 40] [--time-s 6.0]

Serves the file with the Rerun CLI's web viewer on loopback, opens it in headless
Chromium (software WebGL through SwiftShader) and takes the picture over the
DevTools protocol once the viewer has drawn.  Needs ``chromium`` (Debian package)
and ``websocket-client`` (any Python); not a dependency of the testbed.
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rerun_binary() -> str:
    try:
        import rerun_cli

        return str(Path(rerun_cli.__file__).parent / "rerun")
    except ImportError:
        return shutil.which("rerun") or "rerun"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("rrd")
    ap.add_argument("png")
    ap.add_argument("--wait", type=float, default=40.0, help="seconds to let the viewer load and draw")
    ap.add_argument("--size", default="1700,1000")
    ap.add_argument("--rerun", default=os.environ.get("RERUN_BIN") or rerun_binary())
    args = ap.parse_args()
    import websocket  # websocket-client

    web, grpc, dbg = free_port(), free_port(), free_port()
    env = dict(os.environ, RERUN_ANALYTICS="0")
    srv = subprocess.Popen([args.rerun, "--serve-web", args.rrd, "--bind", "127.0.0.1", "--web-viewer-port", str(web),
                            "--port", str(grpc)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                           start_new_session=True, env=env)
    prof = tempfile.mkdtemp(prefix="chromium-")
    w, h = args.size.split(",")
    chrome = None
    try:
        time.sleep(2.0)
        url = (f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}%2Fproxy&renderer=webgl")
        chrome = subprocess.Popen(
            ["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={prof}", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
             f"--window-size={w},{h}", f"--remote-debugging-port={dbg}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        for _ in range(100):
            try:
                tabs = json.load(urllib.request.urlopen(f"http://127.0.0.1:{dbg}/json"))
                page = next(t for t in tabs if t.get("type") == "page")
                break
            except Exception:  # noqa: BLE001 - chromium still starting
                time.sleep(0.2)
        else:
            raise SystemExit("chromium did not come up")
        ws = websocket.create_connection(page["webSocketDebuggerUrl"], timeout=120, suppress_origin=True)
        ids = iter(range(1, 10**6))

        def call(method, **params):
            i = next(ids)
            ws.send(json.dumps({"id": i, "method": method, "params": params}))
            while True:
                m = json.loads(ws.recv())
                if m.get("id") == i:
                    return m.get("result", {})

        call("Emulation.setDeviceMetricsOverride", width=int(w), height=int(h), deviceScaleFactor=1, mobile=False)
        call("Page.navigate", url=url)
        time.sleep(args.wait)
        shot = call("Page.captureScreenshot", format="png")
        Path(args.png).write_bytes(base64.b64decode(shot["data"]))
        ws.close()
        print(f"wrote {args.png}")
    finally:
        for p in (chrome, srv):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
                try:
                    p.wait(5)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
        shutil.rmtree(prof, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
