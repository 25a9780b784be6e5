"""A headless Chromium screenshot of a live page, over the DevTools protocol (the page's websocket needs real time).

`chromium --screenshot` returns before a viewer's scene has arrived; here the page loads, `ready()` is polled
until the server says it has shown something, and only then is the screenshot taken.

Chromium runs in its own process group with a profile folder this module owns: on exit the whole group
(browser, renderers, GPU and crash-reporter helpers) is stopped and waited for before the folder is
removed, and a file a dying helper still writes there cannot fail the test (`close_browser`). Its DevTools
port is the one it picked itself (`_devtools_port`), not one chosen here that another process could take first.
"""
from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

FLAGS = ("--headless=new", "--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--hide-scrollbars", "--no-first-run", "--mute-audio", "--disable-breakpad", "--no-default-browser-check")


def find_chromium() -> str | None:
    return next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)


def _devtools_port(profile: Path) -> int | None:
    """The port Chromium's DevTools listens on (it was started with port 0: it picks a free one and writes it
    into the profile, so no other process can take it between our choosing and its binding), or None yet."""
    try:
        first = (profile / "DevToolsActivePort").read_text().splitlines()[0]
    except (OSError, IndexError):
        return None
    return int(first) if first.isdigit() else None


def screenshot(url: str, out: Path, ready: Callable[[], bool], size: tuple[int, int] = (1000, 700), timeout_s: float = 120.0,
               settle_s: float = 1.0) -> Path:
    """Open `url` in headless Chromium, wait until `ready()` (then `settle_s` more), write a PNG to `out`."""
    from websockets.sync.client import connect

    browser = find_chromium()
    if browser is None:
        raise FileNotFoundError("no Chromium")
    profile = Path(tempfile.mkdtemp(prefix="recon-chromium-"))
    proc = subprocess.Popen([browser, *FLAGS, f"--window-size={size[0]},{size[1]}", "--remote-debugging-port=0",
                             f"--user-data-dir={profile}", "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + timeout_s
        targets = None
        while targets is None:
            port = _devtools_port(profile)
            try:
                if port is not None:
                    with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
                        targets = [t for t in json.load(r) if t.get("type") == "page"] or None
            except OSError:
                pass
            if proc.poll() is not None:
                raise RuntimeError(f"Chromium exited with code {proc.returncode} before its DevTools endpoint came up")
            if time.monotonic() > deadline:
                raise TimeoutError("Chromium's DevTools endpoint did not come up")
            time.sleep(0.3)
        with connect(targets[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=30) as ws:
            ids = iter(range(1, 1_000_000))

            def call(method: str, **params: object) -> dict:
                i = next(ids)
                ws.send(json.dumps({"id": i, "method": method, "params": params}))
                while True:
                    msg = json.loads(ws.recv(timeout=max(1.0, deadline - time.monotonic())))
                    if msg.get("id") == i:
                        return msg.get("result", {})

            call("Page.navigate", url=url)
            while not ready():
                if time.monotonic() > deadline:
                    raise TimeoutError(f"the page at {url} did not become ready in {timeout_s:.0f} s")
                time.sleep(0.5)
            time.sleep(settle_s)
            data = call("Page.captureScreenshot", format="png")["data"]
        out.write_bytes(base64.b64decode(data))
        return out
    finally:
        close_browser(proc, profile)


def _group_alive(pgid: int) -> bool:
    """Whether a running (not zombie) process is left in the group: a container's init may never reap zombies."""
    proc_fs = Path("/proc")
    if not proc_fs.is_dir():
        try:
            os.killpg(pgid, 0)
        except (ProcessLookupError, PermissionError):
            return False
        return True
    for stat in proc_fs.glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()  # after "pid (comm)": state, ppid, pgrp, ...
        except (OSError, IndexError):
            continue  # the process exited while we looked
        if int(fields[2]) == pgid and fields[0] not in ("Z", "X"):
            return True
    return False


def close_browser(proc: subprocess.Popen, profile: Path, wait_s: float = 10.0) -> None:
    """Stop Chromium and every process it started (SIGTERM, then SIGKILL), wait for them, remove its profile.

    Why: terminating only the browser process left helpers writing into the profile while it was being
    removed (`OSError: Directory not empty: 'Default'`). Leftovers that still cannot be removed are ignored:
    the profile is a temporary folder, never worth failing a test over.
    """
    pgid = proc.pid  # start_new_session=True: the browser leads its own process group
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(pgid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(timeout=wait_s)
        except subprocess.TimeoutExpired:
            continue
        deadline = time.monotonic() + wait_s
        while _group_alive(pgid) and time.monotonic() < deadline:
            time.sleep(0.1)  # helpers that outlive the browser (reaped by init, not by us)
        if not _group_alive(pgid):
            break
    if proc.poll() is None:
        proc.kill()
        proc.wait()
    shutil.rmtree(profile, ignore_errors=True)
