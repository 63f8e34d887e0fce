"""Issue 49, item 5 on the session page (`teleop serve` in headless Chromium): when the server stops, a
banner across the page says "disconnected from the server: reconnecting..."; when a server is back on the
same port, the banner goes and the page shows the new server's session (viser sends it whole again). The
first server runs with `--keep-scene` (item 1: the flag reaches the session), the second without.
"""

from __future__ import annotations

from tests import browser as headless

PAGE_SIZE = (900, 600)  # software WebGL: fewer pixels, faster frames
BANNER = "document.getElementById('teleop-disconnected')"


def test_the_session_page_shows_a_banner_while_the_server_is_gone(browser, tmp_path):
    server = headless.ServeProcess(["--device", "gizmo", "--seed", "3", "--keep-scene"], tmp_path)
    page = None
    try:
        assert server.status()["fresh_episodes"] is False  # --keep-scene: Save leaves the scene as it is (item 1)
        page = headless.open_page(browser, server.url, size=PAGE_SIZE)
        page.bring_to_front()  # viser's client reconnects only while its page has the focus
        page.wait_for_function("window.__teleopInput && window.__teleopInput.connected()", timeout=60_000)
        assert page.evaluate(f"{BANNER} === null")
        server.stop()
        page.wait_for_function(f"{BANNER} !== null && {BANNER}.isConnected", timeout=30_000)
        assert page.locator("#teleop-disconnected").inner_text() == "disconnected from the server: reconnecting…"
        assert page.locator("#teleop-disconnected").is_visible()
        server = headless.ServeProcess(["--device", "gizmo", "--seed", "7"], tmp_path, port=server.port)
        page.wait_for_function(f"({BANNER} === null || !{BANNER}.isConnected)"
                               " && document.documentElement.dataset.teleopConnection === 'ok'", timeout=90_000)
        server.wait_for(lambda s: s["clients"] >= 1, timeout_s=30, what="the page to reconnect to the new server")
        page.get_by_text("seed 7").first.wait_for(timeout=30_000)  # the new server's panel, not the last one's
        assert server.status()["fresh_episodes"] is True  # the default: every episode from its seed's initial state
        assert page.evaluate("window.__teleopInput.connected()")
    finally:
        if page is not None:
            page.close()
        server.stop()
