"""The built book in a real browser: headless Chromium over a local static server, with no network.

Serves ``_build/html`` on a free localhost port, opens the index, every page of the theory part and every
page that holds an explorer slider (``pinnhjb.widgets.FrameExplorer.html``), and checks that

* the math rendered (MathJax output present, no raw ``$$`` / ``\\(`` / ``\\[`` left in the visible text,
  no MathJax error nodes),
* every ``<img>`` loaded (``naturalWidth > 0``),
* no request left localhost, and no local request failed or returned an error status,
* moving a slider changes the displayed frame and its value label.

A screenshot of every page is saved under ``_build/screenshots/``. Skipped when ``_build/html``, Chromium
or Playwright is missing, unless ``PINNHJB_REQUIRE_SITE=1`` (set by ``.ci/run``), which turns every skip
into a failure. Build the site first: ``bash scripts/build_book.sh`` (``scripts/test.sh`` does it).
"""
from __future__ import annotations

import functools
import http.server
import os
import re
import shutil
import threading
from pathlib import Path
from urllib.parse import urlparse

import pytest

ROOT = Path(__file__).resolve().parents[1]
SITE = Path(os.environ.get("PINNHJB_SITE", ROOT / "_build" / "html"))  # the built site (override for a copy)
SHOTS = SITE.parent / "screenshots"
REQUIRE = os.environ.get("PINNHJB_REQUIRE_SITE") == "1"
CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run",
                  "--disable-default-apps", "--disable-extensions"]
EXPLORER_MARK = 'class="pinnhjb-explorer"'
WIDGET_VIEW_MARK = "application/vnd.jupyter.widget-view+json"
WIDGET_STATE_MARK = "application/vnd.jupyter.widget-state+json"


def _missing(reason: str):
    """Skip, or fail when the site test is required (CI)."""
    if REQUIRE:
        pytest.fail(f"PINNHJB_REQUIRE_SITE=1 but {reason}")
    pytest.skip(reason)


def _chromium() -> str | None:
    for cand in (os.environ.get("PINNHJB_CHROMIUM"), "/usr/bin/chromium", shutil.which("chromium"),
                 shutil.which("chromium-browser")):
        if cand and Path(cand).is_file() and os.access(cand, os.X_OK):
            return cand
    return None


def _content_pages() -> list[Path]:
    """Every page of the book itself (not the search/genindex pages or the redirecting index)."""
    return sorted(p for p in SITE.rglob("*.html")
                  if p.parent != SITE and not p.relative_to(SITE).parts[0].startswith("_"))


def _pages_to_open() -> list[str]:
    """The index, the theory pages and every page holding an explorer, as paths relative to the site."""
    pages = ["index.html"]
    for p in _content_pages():
        rel = p.relative_to(SITE).as_posix()
        if rel.startswith("book/") or EXPLORER_MARK in p.read_text(encoding="utf-8"):
            pages.append(rel)
    return pages


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):  # keep pytest output clean
        pass


@pytest.fixture(scope="module")
def server():
    if not (SITE / "index.html").is_file():
        _missing(f"no built site at {SITE} (run: bash scripts/build_book.sh)")
    handler = functools.partial(_QuietHandler, directory=str(SITE))
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)  # port 0: a free port
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()


@pytest.fixture(scope="module")
def browser():
    exe = _chromium()
    if exe is None:
        _missing("no Chromium found (apt-get install -y chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        _missing("playwright is not installed (pip install -r requirements.txt)")
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=exe, headless=True, args=CHROMIUM_FLAGS)
        try:
            yield b
        finally:
            b.close()


def _open(browser, server, rel: str):
    """Open one page, recording every request; returns (page, requests, failures)."""
    context = browser.new_context(viewport={"width": 1280, "height": 900}, service_workers="block")
    page = context.new_page()
    requests: list[str] = []
    failures: list[str] = []
    page.on("request", lambda r: requests.append(r.url))
    page.on("requestfailed", lambda r: failures.append(f"{r.url} ({r.failure})"))
    page.on("response", lambda r: failures.append(f"{r.url} (HTTP {r.status})") if r.status >= 400 else None)
    page.goto(f"{server}/{rel}", wait_until="load")
    redirect = re.search(r'http-equiv="Refresh" content="0; url=([^"]+)"', (SITE / rel).read_text(encoding="utf-8"),
                         re.IGNORECASE)
    if redirect:  # Jupyter Book's index.html only redirects to the root page: check where it lands
        page.wait_for_url(f"**/{redirect.group(1)}", wait_until="load")
    return context, page, requests, failures


def _wait_for_math(page):
    """Wait until MathJax (if the page has math) has typeset everything."""
    has_math = page.evaluate("() => document.querySelector('.math') !== null")
    if has_math:
        try:
            page.wait_for_function("() => window.MathJax && MathJax.startup && MathJax.startup.promise",
                                   timeout=30_000)
        except Exception as exc:  # playwright's TimeoutError
            raise AssertionError(f"{page.url}: the page has math but MathJax never started") \
                from exc
        page.evaluate("() => MathJax.startup.promise")
    return has_math


def _check_page(page, requests, failures, server, rel):
    host = urlparse(server).netloc
    page.evaluate("() => window.scrollTo(0, document.body.scrollHeight)")  # anything loaded lazily, too
    page.wait_for_load_state("networkidle")
    page.evaluate("() => window.scrollTo(0, 0)")

    external = [u for u in requests if urlparse(u).scheme in ("http", "https", "ws", "wss")
                and urlparse(u).netloc != host]
    assert not external, f"{rel}: requests left the machine: {external}"
    assert not failures, f"{rel}: failed requests: {failures}"
    has_math = _wait_for_math(page)

    if has_math:
        n_math = page.evaluate("() => document.querySelectorAll('.math').length")
        n_out = page.evaluate("() => document.querySelectorAll('mjx-container').length")
        assert n_out >= n_math > 0, f"{rel}: {n_math} math elements but {n_out} rendered by MathJax"
        assert page.evaluate("() => document.querySelectorAll('mjx-merror').length") == 0, \
            f"{rel}: MathJax reported an error"
        text = page.evaluate("""() => {  // prose only: not code, scripts or MathJax's own output
            const walk = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);  // sidebar too
            const out = [];
            for (let n = walk.nextNode(); n; n = walk.nextNode())
                if (!n.parentElement.closest('pre, code, script, style, textarea, mjx-container'))
                    out.push(n.textContent);
            return out.join(' ');
        }""")
        raw = re.findall(r"\$\$|\\\(|\\\)|\\\[|\\\]|\\begin\{", text)
        assert not raw, f"{rel}: raw TeX left visible: {raw[:5]}"

    broken = page.evaluate("""() => Array.from(document.images)
        .filter(im => im.getBoundingClientRect().width > 0 || im.closest('.pinnhjb-frames'))
        .filter(im => !(im.complete && im.naturalWidth > 0))
        .map(im => (im.currentSrc || im.src).slice(0, 80))""")
    assert not broken, f"{rel}: images not loaded: {broken}"
    n_bad = page.evaluate("""() => Array.from(document.images)
        .filter(im => !(im.complete && im.naturalWidth > 0)).length""")
    assert n_bad == 0, f"{rel}: {n_bad} images (hidden or not) did not load"

    assert WIDGET_VIEW_MARK not in page.content(), (
        f"{rel}: a widget view needs the ipywidgets manager, which the offline site does not load")
    return has_math


def _move_sliders(page, rel):
    """Move every explorer slider and check that the displayed frame and the label change."""
    explorers = page.locator(".pinnhjb-explorer")
    n = explorers.count()
    for k in range(n):
        ex = explorers.nth(k)
        ex.scroll_into_view_if_needed()
        state = """el => {
            const shown = Array.from(el.querySelectorAll('.pinnhjb-frames img'))
                .filter(im => getComputedStyle(im).display !== 'none');
            return {shown: shown.map(im => im.dataset.i), src: shown.length ? shown[0].src.slice(-64) : null,
                    label: el.querySelector('.pinnhjb-value').textContent,
                    value: el.querySelector('input[type=range]').value,
                    max: el.querySelector('input[type=range]').max,
                    width: shown.length ? shown[0].naturalWidth : 0};
        }"""
        before = ex.evaluate(state)
        assert len(before["shown"]) == 1 and before["width"] > 0, f"{rel}: explorer {k} shows {before}"
        assert int(before["max"]) >= 1, f"{rel}: explorer {k} has a single frame"
        slider = ex.locator("input[type=range]")
        slider.focus()
        key = "ArrowRight" if int(before["value"]) < int(before["max"]) else "ArrowLeft"
        page.keyboard.press(key)  # a real user input: fires the 'input' event the explorer listens to
        after = ex.evaluate(state)
        assert after["value"] != before["value"], f"{rel}: explorer {k}: the slider did not move"
        assert len(after["shown"]) == 1 and after["shown"] != before["shown"], \
            f"{rel}: explorer {k}: moving the slider did not change the frame ({before} -> {after})"
        assert after["src"] != before["src"] and after["width"] > 0, f"{rel}: explorer {k}: same image shown"
        assert after["label"] != before["label"], f"{rel}: explorer {k}: the value label did not change"
    return n


def test_site_built_and_has_explorers():
    if not (SITE / "index.html").is_file():
        _missing(f"no built site at {SITE} (run: bash scripts/build_book.sh)")
    pages = _pages_to_open()
    assert any(p.startswith("notebooks/") for p in pages), "no page with an explorer slider in the built site"
    for p in _content_pages():  # the offline site references no CDN in any page
        html = p.read_text(encoding="utf-8")
        ext = re.findall(r'<(?:script|link|img|iframe)[^>]+(?:src|href)="(https?://[^"]+)"', html)
        assert not ext, f"{p.relative_to(SITE)} loads assets from the network: {ext}"
        assert WIDGET_STATE_MARK not in html, f"{p.relative_to(SITE)} embeds ipywidgets state that nothing reads"


def test_pages_in_chromium(server, browser):
    SHOTS.mkdir(parents=True, exist_ok=True)
    pages = _pages_to_open()
    n_math = n_sliders = 0
    for rel in pages:
        context, page, requests, failures = _open(browser, server, rel)
        try:
            n_math += bool(_check_page(page, requests, failures, server, rel))
            moved = _move_sliders(page, rel)
            n_sliders += moved
            if moved:  # show the first explorer, after its slider was moved
                page.locator(".pinnhjb-explorer").first.scroll_into_view_if_needed()
            page.screenshot(path=str(SHOTS / (rel.replace("/", "__").removesuffix(".html") + ".png")),
                            full_page=False)
            assert not failures, f"{rel}: failed requests after interaction: {failures}"
        finally:
            context.close()
    assert n_math > 0, "no page with math was checked"
    assert n_sliders > 0, "no explorer slider was moved"
