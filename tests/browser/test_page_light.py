"""The page stays light: what its first render loads (the 3D viewer's three.js comes later, with a
result) and how long the first render takes in Debian's Chromium against a real `spine serve`.
docs/web.md records the figures this test prints, with the date and the command."""

from __future__ import annotations

import gzip
import json
from typing import Any

import httpx
import pytest
from page_fixtures import open_page

from services.api.web import STATIC_DIR

pytestmark = pytest.mark.browser

# Budget of the first render's assets (HTML + CSS + JS, gzip): the page's own choice, recorded in
# docs/web.md; it holds the page without three.js, which is loaded with the first result.
FIRST_RENDER_GZIP_BUDGET = 64 * 1024
# web.dev's "good" First Contentful Paint (Core Web Vitals guidance): at most 1.8 s.
FCP_GOOD_MS = 1800.0


def test_first_render_is_small_and_fast(
    browser: Any, live_url: str, api_key: str, capsys: pytest.CaptureFixture[str]
) -> None:
    context, page, watch = open_page(browser, live_url + "/", None)
    timing = page.evaluate("""() => {
        const nav = performance.getEntriesByType('navigation')[0];
        const fcp = performance.getEntriesByName('first-contentful-paint')[0];
        return {fcp_ms: fcp ? fcp.startTime : null, dom_content_loaded_ms: nav.domContentLoadedEventEnd,
                load_ms: nav.loadEventEnd};
    }""")
    loaded = [r.url for r in watch.requests if r.url.startswith(live_url) and "/assets/" in r.url]
    assert loaded and not any("viewer3d" in u for u in loaded), loaded  # three.js not in the first render
    sizes = {"index.html": len(gzip.compress(httpx.get(live_url + "/").content))}
    for url in loaded:
        sizes[url.rsplit("/", 1)[-1]] = len(gzip.compress(httpx.get(url).content))
    total = sum(sizes.values())
    raw = {p.name: p.stat().st_size for p in (STATIC_DIR / "assets").iterdir()}
    with capsys.disabled():
        print("\nfirst render:", json.dumps({"timing": timing, "gzip_bytes": sizes, "gzip_total": total}))
        print("built assets (bytes):", json.dumps(raw))
    assert total <= FIRST_RENDER_GZIP_BUDGET, sizes
    assert timing["fcp_ms"] is not None and timing["fcp_ms"] <= FCP_GOOD_MS, timing
    assert not watch.foreign and not watch.errors
    context.close()
