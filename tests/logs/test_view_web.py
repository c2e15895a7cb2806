"""`l2r view --web` in a real browser: the URL it prints opens the recording, not the viewer's
welcome page. Needs Chromium (apt-get install chromium) and playwright (the dev extra); skipped
without them."""

from __future__ import annotations

import re
import shutil
import signal
import subprocess
import sys

import pytest

from tests.conftest import free_port
from tests.logs.test_view import episodes  # noqa: F401  (the fixture)

sync_api = pytest.importorskip("playwright.sync_api")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium on this machine")
def test_the_printed_url_opens_the_recording_in_a_browser(episodes):  # noqa: F811
    web_port, grpc_port = free_port(), free_port()
    viewer = subprocess.Popen(
        [sys.executable, "-m", "l2r.cli", "view", str(episodes[0][0]), "--web", "--web-port", str(web_port),
         "--grpc-port", str(grpc_port)], stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        printed = ""
        while "(Ctrl-C stops)" not in printed and viewer.poll() is None:
            printed += viewer.stderr.readline()
        url = re.search(r"open (http://\S+)", printed)
        assert url, printed
        # The viewer fetches the recording from the gRPC server's proxy: that answer is the proof
        # it opened the recording (the welcome page asks it for nothing).
        with sync_api.sync_playwright() as playwright:
            browser = playwright.chromium.launch(
                executable_path=CHROMIUM, args=["--no-sandbox", "--use-gl=swiftshader", "--enable-unsafe-swiftshader"])
            page = browser.new_page()
            with page.expect_response(lambda r: f":{grpc_port}/" in r.url and r.ok, timeout=90_000):
                page.goto(url.group(1))
            browser.close()
    finally:
        viewer.send_signal(signal.SIGINT)
        viewer.wait(timeout=30)
