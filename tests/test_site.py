"""The built book in a real browser: headless Chromium over a local static server, with no network.

Serves ``_build/html`` on a free localhost port and opens EVERY content page (the root page, the theory and
reference pages under ``book/``, every chapter under ``notebooks/``) at a desktop size (1400 x 900), a laptop
size (1280 x 800: from 1200 px both sidebars show and the text's column is at its narrowest) and a phone size
(390 x 844). One sweep (the ``sweep`` fixture) visits every page at every size and records what each
check finds; each test below then reports every offending page and element of its check in one message, so a
failing run says everything that is wrong at once.

The shell (theme, configuration, ``book/_ext``, ``book/_theme``):

* the math rendered (MathJax output present, no raw ``$$`` / ``\\(`` / ``\\[`` left, no MathJax error nodes);
* every ``<img>`` loaded; no request left localhost; no local request failed; no page holds a widget view;
* no console errors (console messages of type error, and uncaught page errors);
* on a phone the navigation drawer opens when its (visible) menu button is pressed and shows links a finger
  can reach, and the contents button shows the page's sections; on a desktop the menu button hides the
  sidebar and shows it again;
* one search box on the desktop, and the search page finds words offline;
* no horizontal page overflow (``document.scrollingElement.scrollWidth <= innerWidth + 1``), and no wide
  equation, table, figure or code block is cut off by a box that does not scroll;
* every figure keeps its aspect ratio;
* each explorer slider, moved, changes the displayed frame and its value label.

The content (chapters and theory pages):

* no visible code input block (``div.cell_input pre``, ``div.highlight pre``) scrolls sideways, nor a printed
  output (they wrap in their box); on the desktop none even wraps (``book/_theme/pinnhjb.js`` wraps a block
  wider than its box, as on a phone), nor on the laptop in a chapter: its lines fit the column (77 characters);
  where a line of code wraps, its other rows hang right of where its code starts, not back at the left edge;
* every display equation fits its column, on a phone too: ``book/_theme/pinnhjb.js`` draws a wide one smaller,
  down to 0.7 of its size, and beyond that the equation must be written on more lines; and no inline formula is
  wider than its line (one that is gets the class ``pinnhjb-wide`` and scrolls: make it a display equation);
  an inline formula is glued to the punctuation after it and to an opening bracket before it (``pinnhjb.js``),
  so no line starts with a full stop or ends with "("; and a box that fits draws no "more this way" shadow
  (it left a faint line at the edge of every equation on a phone);
* every raster figure (``img`` in cell outputs, figures and explorer sliders) displays at >= 0.75 of its
  intended width, on the desktop and on a phone (where it scrolls sideways in its own box): its ``width``
  attribute when set (a 2x "retina" PNG carries width = natural / 2), else its inline style width in px (how
  MyST-NB writes an output's width), else naturalWidth; a figure's box that scrolls fades at the edge past
  which more of it lies (``pinnhjb.js``), and scrolls without its caption;
* no raw label or role in the visible text (``eq. (flow_res)``, ``(IHJB_res)``, ``[third]``, ``{eq}``,
  ``{cite}``, ``eq-...``);
* every chapter links to a page of the book's theory part.

A full-page screenshot of every page at every size goes to ``_build/screenshots/`` (``<page>__desktop.png``,
``<page>__laptop.png``, ``<page>__phone.png``). Skipped when ``_build/html``, Chromium or Playwright is missing,
unless ``PINNHJB_REQUIRE_SITE=1`` (set by ``.ci/run``), which turns every skip into a failure. Build the site first:
``bash scripts/build_book.sh`` (``scripts/test.sh`` does it). ``PINNHJB_SITE`` points the test at another
built site (e.g. a quick build without notebook execution).
"""

from __future__ import annotations

import functools
import http.server
import io
import os
import re
import shutil
import threading
from collections import defaultdict
from pathlib import Path
from urllib.parse import unquote, urlparse

import pytest

ROOT = Path(__file__).resolve().parents[1]
SITE = Path(os.environ.get("PINNHJB_SITE", ROOT / "_build" / "html"))  # the built site (override for a copy)
SHOTS = SITE.parent / "screenshots"
REQUIRE = os.environ.get("PINNHJB_REQUIRE_SITE") == "1"
CHROMIUM_FLAGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-default-apps",
    "--disable-extensions",
]
EXPLORER_MARK = 'class="pinnhjb-explorer"'
WIDGET_VIEW_MARK = "application/vnd.jupyter.widget-view+json"
WIDGET_STATE_MARK = "application/vnd.jupyter.widget-state+json"
SIZES = {"desktop": (1400, 900), "laptop": (1280, 800), "phone": (390, 844)}
MIN_FIGURE_SCALE = 0.75  # a raster figure shows at no less than this fraction of its intended width
MIN_DRAWER_LINKS = 3  # an open navigation drawer shows at least this many reachable links

# Raw labels, keys and roles that should have become links or numbers. Checked in all visible text except code
# inputs, inline code and MathJax's output; ROLE_KEY only in prose (printed outputs hold e.g. "[nan]").
RAW_LABEL_PATTERNS = {
    "a MyST role left as text": re.compile(
        r"\{(?:eq|cite(?::[a-z]+)?|ref|numref|doc|prf:[a-z]+|term|download|glue(?::[a-z]+)?)\}"
    ),
    "an equation named by its label": re.compile(r"\beqs?\.\s*\((?=[^)\s]*[A-Za-z])[\w:.-]+\)"),
    "a label in parentheses": re.compile(r"\((?=[\w-]*[A-Za-z])[A-Za-z0-9]+_[\w-]+\)"),
    "an eq- label": re.compile(r"(?<![\w-])eq-[\w-]+"),
    "an equation number in double parentheses": re.compile(r"\(\(\d+(?:\.\d+)*\)\)"),  # ({eq}`x`)
}
ROLE_KEY = re.compile(r"\[(?=[a-z0-9_:-]*[a-z]{2})[a-z][a-z0-9_:-]*\]")  # [third]: an unresolved citation key


def _missing(reason: str):
    """Skip, or fail when the site test is required (CI)."""
    if REQUIRE:
        pytest.fail(f"PINNHJB_REQUIRE_SITE=1 but {reason}")
    pytest.skip(reason)


def _chromium() -> str | None:
    for cand in (
        os.environ.get("PINNHJB_CHROMIUM"),
        "/usr/bin/chromium",
        shutil.which("chromium"),
        shutil.which("chromium-browser"),
    ):
        if cand and Path(cand).is_file() and os.access(cand, os.X_OK):
            return cand
    return None


def _content_pages() -> list[Path]:
    """Every page of the book itself (not the search/genindex pages or the redirecting index)."""
    return sorted(
        p for p in SITE.rglob("*.html") if p.parent != SITE and not p.relative_to(SITE).parts[0].startswith("_")
    )


def _rel(p: Path) -> str:
    return p.relative_to(SITE).as_posix()


def _chapters() -> list[str]:
    return [r for r in map(_rel, _content_pages()) if r.startswith("notebooks/")]


def _theory_pages() -> set[str]:
    """The pages of the toc part whose caption names the theory (every book/ page if there is none)."""
    import yaml  # PyYAML comes with Jupyter Book

    toc = yaml.safe_load((ROOT / "_toc.yml").read_text(encoding="utf-8"))
    pages = {
        Path(ch["file"]).with_suffix(".html").as_posix()
        for part in toc.get("parts", [])
        if "theory" in str(part.get("caption", "")).lower()
        for ch in part.get("chapters", [])
    }
    return pages or {r for r in map(_rel, _content_pages()) if r.startswith("book/")}


def _has_explorer(rel: str) -> bool:
    return EXPLORER_MARK in (SITE / rel).read_text(encoding="utf-8")


SHOT_TILE = 8000  # CSS px; one full-page capture much taller than this comes back with its text blank


def _full_page_shot(page, path: Path) -> None:
    """The whole page as one PNG at ``path``. Chromium leaves the text of a very tall full-page capture blank
    (chapter 8 is over 35000 px), so a tall page is captured in clips of ``SHOT_TILE`` px and stitched. The clips
    are taken from one window as tall as the page, set once: a full-page capture per clip resizes the window for
    each, and the theme's layout, redone on each resize, came back shifted and cut at a seam (chapter 10's last
    clip, 2026-12-06). The window gets its own size back afterwards."""
    height = page.evaluate("() => document.documentElement.scrollHeight")
    if height <= SHOT_TILE:
        page.screenshot(path=str(path), full_page=True)
        return
    from PIL import Image

    window = dict(page.viewport_size)
    try:
        for _ in range(5):  # a window as tall as the page can change the page's height (vh units): until it holds
            page.set_viewport_size({"width": window["width"], "height": height})
            page.wait_for_timeout(300)
            now = page.evaluate("() => document.documentElement.scrollHeight")
            if now == height:
                break
            height = now
        tiles = []
        for y in range(0, height, SHOT_TILE):
            clip = dict(x=0, y=y, width=window["width"], height=min(SHOT_TILE, height - y))
            tiles.append(Image.open(io.BytesIO(page.screenshot(clip=clip))))
    finally:
        page.set_viewport_size(window)
    sheet = Image.new("RGB", (tiles[0].width, sum(t.height for t in tiles)), "white")
    top = 0
    for tile in tiles:  # in device pixels, each tile below the last
        sheet.paste(tile, (0, top))
        top += tile.height
    sheet.save(path)


def _shot_name(rel: str, size: str) -> str:
    return rel.replace("/", "__").removesuffix(".html") + f"__{size}.png"


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


class _Visit:
    """One page open at one size, with everything it requested and logged."""

    def __init__(self, browser, server, rel: str, size: str):
        width, height = SIZES[size]
        self.rel, self.size, self.host = rel, size, urlparse(server).netloc
        self.where = f"{rel} [{size}]"
        self.context = browser.new_context(viewport={"width": width, "height": height}, service_workers="block")
        self.page = page = self.context.new_page()
        page.set_default_timeout(30_000)
        self.requests: list[str] = []
        self.failures: list[str] = []
        self.errors: list[str] = []
        page.on("request", lambda r: self.requests.append(r.url))
        page.on("requestfailed", lambda r: self.failures.append(f"{r.url} ({r.failure})"))
        page.on("response", lambda r: self.failures.append(f"{r.url} (HTTP {r.status})") if r.status >= 400 else None)
        page.on("console", lambda m: self.errors.append(f"console error: {m.text}") if m.type == "error" else None)
        page.on("pageerror", lambda e: self.errors.append(f"page error: {e}"))
        page.goto(f"{server}/{rel}", wait_until="load")
        redirect = re.search(
            r'http-equiv="Refresh" content="0; url=([^"]+)"',
            (SITE / rel.split("?")[0]).read_text(encoding="utf-8"),
            re.IGNORECASE,
        )
        if redirect:  # Jupyter Book's index.html only redirects to the root page: check where it lands
            page.wait_for_url(f"**/{redirect.group(1)}", wait_until="load")
        page.evaluate("() => window.scrollTo(0, document.body.scrollHeight)")  # anything loaded lazily, too
        page.wait_for_load_state("networkidle")
        page.evaluate("() => window.scrollTo(0, 0)")

    def external_requests(self) -> list[str]:
        return [
            u
            for u in self.requests
            if urlparse(u).scheme in ("http", "https", "ws", "wss") and urlparse(u).netloc != self.host
        ]

    def close(self):
        self.context.close()


def _wait_for_math(page) -> bool:
    """Wait until MathJax (if the page has math) has typeset everything; True when the page has math."""
    if not page.evaluate("() => document.querySelector('.math') !== null"):
        return False
    try:
        page.wait_for_function("() => window.MathJax && MathJax.startup && MathJax.startup.promise", timeout=30_000)
    except Exception as exc:  # playwright's TimeoutError
        raise AssertionError(f"{page.url}: the page has math but MathJax never started") from exc
    page.evaluate("() => MathJax.startup.promise")
    return True


# --- what the sweep measures in the page ------------------------------------------------------------------

_IS_SHOWN = """el => el.getClientRects().length > 0 && (!el.checkVisibility ||
                    el.checkVisibility({visibilityProperty: true, opacityProperty: true}))"""

_MATH_STATE = """() => {
    const text = [];  // prose only: not code, scripts or MathJax's own output
    const walk = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);  // the sidebar too
    for (let n = walk.nextNode(); n; n = walk.nextNode())
        if (!n.parentElement.closest('pre, code, script, style, textarea, mjx-container')) text.push(n.textContent);
    return {n_math: document.querySelectorAll('.math').length,
            n_out: document.querySelectorAll('mjx-container').length,
            n_err: document.querySelectorAll('mjx-merror').length, text: text.join(' ')};
}"""

_IMAGES_BROKEN = """() => Array.from(document.images)
    .filter(im => !(im.complete && im.naturalWidth > 0))
    .map(im => (im.currentSrc || im.src).slice(-80))"""

_VISIBLE_TEXT = (
    """() => {
    const shown = (%s);
    const prose = [], outputs = [];
    const walk = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
    for (let n = walk.nextNode(); n; n = walk.nextNode()) {
        const el = n.parentElement;
        if (!el || !n.textContent.trim()) continue;
        if (el.closest('div.cell_input, code, kbd, script, style, textarea, mjx-container, dialog:not([open])'))
            continue;
        if (!shown(el)) continue;
        (el.closest('pre') ? outputs : prose).push(n.textContent);
    }
    return {prose: prose.join(' '), outputs: outputs.join(' ')};
}"""
    % _IS_SHOWN
)


def _scrolling(blocks: str, wider: str = "pre.scrollWidth > pre.clientWidth + 1") -> str:
    """JavaScript that returns the shown ``<pre>`` boxes among ``blocks`` (a JavaScript expression giving an array
    of them) wider than their box (``wider``, a JavaScript condition on ``pre``): by how much, the box's width,
    which cell (or block) and its longest line."""
    return """() => {
    const shown = (%s);
    const blocks = %s;
    const cells = Array.from(document.querySelectorAll('div.cell'));
    return blocks
        .filter(pre => shown(pre) && (%s))
        .map(pre => {
            const lines = pre.innerText.split('\\n');
            const longest = lines.reduce((a, b) => (b.length > a.length ? b : a), '');
            const cell = pre.closest('div.cell');
            const where = cell ? 'code cell ' + (cells.indexOf(cell) + 1) : 'code block ' + (blocks.indexOf(pre) + 1);
            return {over: pre.scrollWidth - pre.clientWidth, width: pre.clientWidth, where,
                    line: longest.trim().slice(0, 60), chars: longest.length};
        });
}""" % (_IS_SHOWN, blocks, wider)


# code the reader is meant to read: cell inputs and code blocks of the text, not printed outputs
_CODE = (
    "Array.from(document.querySelectorAll('div.cell_input pre, div.highlight pre'))"
    ".filter(pre => !pre.closest('.cell_output, .output'))"
)
_CODE_SCROLLING = _scrolling(_CODE)
_CODE_WRAPPED = _scrolling(_CODE, "pre.classList.contains('pinnhjb-wrap')")  # by book/_theme/pinnhjb.js
# lines of code that wrap (on a phone, all long ones) without their other rows hanging right of where the line's
# code starts (book/_theme/pinnhjb.js and .css): those rows would read as lines of their own at the left edge
_CODE_NOT_HANGING = """() => {
    const shown = (%s);
    const blocks = %s;
    const found = [];
    for (const pre of blocks.filter(shown)) {
        const lines = pre.querySelectorAll('span.pinnhjb-line');
        if (!lines.length) { found.push({where: 'a block of ' + pre.innerText.split('\\n').length
                                                  + ' lines', line: 'not split into span.pinnhjb-line'}); continue; }
        for (const line of lines) {
            const walk = document.createTreeWalker(line, NodeFilter.SHOW_TEXT);
            let start = null;  // where the line's code starts: its first character that is not a blank
            for (let t = walk.nextNode(); t && !start; t = walk.nextNode()) {
                const i = t.data.search(/\\S/);
                if (i < 0) continue;
                const r = document.createRange();
                r.setStart(t, i);
                r.setEnd(t, i + 1);
                start = r.getBoundingClientRect();
            }
            if (!start) continue;
            const all = document.createRange();
            all.selectNodeContents(line);
            const later = Array.from(all.getClientRects())
                .filter(b => b.width > 0 && b.top >= start.bottom - 1);
            const back = later.filter(b => b.left < start.left + 1);
            if (back.length)
                found.push({where: 'a line of ' + line.textContent.length + ' characters',
                            line: line.textContent.trim().slice(0, 60),
                            by: Math.round(start.left - Math.min(...back.map(b => b.left)))});
        }
    }
    return found;
}""" % (_IS_SHOWN, _CODE)
# printed outputs, which wrap in their box (book/_theme/pinnhjb.css)
_OUTPUT_SCROLLING = _scrolling(
    "Array.from(document.querySelectorAll('div.cell_output div.output > div.highlight > pre'))"
)

_EQUATIONS_SCROLLING = (
    """() => {
    const shown = (%s);
    return Array.from(document.querySelectorAll(
            'article mjx-container[jax="CHTML"][display="true"], article span.math.pinnhjb-wide'))
        .filter(el => shown(el) && el.scrollWidth - el.clientWidth > 2)
        .map(el => ({over: el.scrollWidth - el.clientWidth, width: el.clientWidth, size: el.style.fontSize,
                     inline: el.tagName === 'SPAN', text: el.textContent.trim().slice(0, 50)}));
}"""
    % _IS_SHOWN
)

# inline formulas with the punctuation after them, or an opening bracket before them, left loose (pinnhjb.js glues
# them together)
_LOOSE_PUNCTUATION = """() => Array.from(document.querySelectorAll('article span.math'))
    .map(el => { const glued = el.parentElement.classList.contains('pinnhjb-glue'), box = glued ? el.parentElement : el;
                 const n = el.nextSibling, p = box.previousSibling, text = t => t && t.nodeType === Node.TEXT_NODE;
                 const after = !glued && text(n) && /^[.,;:!?)\\]]/.test(n.textContent) ? n.textContent[0] : '';
                 const before = text(p) && /[(\\[]$/.test(p.textContent) ? p.textContent.slice(-1) : '';
                 return (after || before) ? before + el.textContent.trim().slice(0, 30) + after : null; })
    .filter(s => s !== null)"""

# boxes that fit but draw the "more this way" shadows (pinnhjb.css draws them on .pinnhjb-scrolls only)
_IDLE_SHADOWS = (
    """() => {
    const shown = (%s);
    return Array.from(document.querySelectorAll(
            'article mjx-container[jax="CHTML"][display="true"], article .pst-scrollable-table-container'))
        .filter(el => shown(el) && el.scrollWidth - el.clientWidth <= 2 &&
                      getComputedStyle(el).backgroundImage.includes('gradient'))
        .map(el => el.textContent.trim().slice(0, 40));
}"""
    % _IS_SHOWN
)

_FIGURES = (
    """() => {
    const shown = (%s);
    return Array.from(document.querySelectorAll(
            'div.cell_output img, figure img, div.figure img, .pinnhjb-explorer img'))
        .filter(im => shown(im) && im.naturalWidth > 0)
        .filter(im => !/\\.svg([?#]|$)|^data:image\\/svg/i.test(im.currentSrc || im.src))
        .map(im => {
            const r = im.getBoundingClientRect();
            const attr = parseFloat(im.getAttribute('width'));
            const style = /px$/.test(im.style.width) ? parseFloat(im.style.width) : NaN;
            const intended = attr > 0 ? attr : (style > 0 ? style : im.naturalWidth);
            const fig = im.closest('figure');
            const number = fig && fig.querySelector('figcaption .caption-number');
            const label = (number ? number.textContent.trim() + ' ' : '') +
                          (im.alt || decodeURIComponent(im.src.split('/').pop()));
            return {shown: r.width, height: r.height, intended, nw: im.naturalWidth, nh: im.naturalHeight,
                    explorer: !!im.closest('.pinnhjb-explorer'),
                    name: label.trim().slice(0, 70)};
        });
}"""
    % _IS_SHOWN
)

# boxes that scroll a figure sideways (on a phone) but do not say so: no fade at the edge with more, or with the
# figure's caption inside the box (it would scroll away as the reader swipes to the rest of the figure)
_FIGURE_BOXES = (
    """() => {
    const shown = (%s);
    return Array.from(document.querySelectorAll('article img'))
        .filter(im => shown(im))
        .map(im => { let el = im.parentElement;
                     while (el && el.tagName !== 'ARTICLE' && getComputedStyle(el).overflowX === 'visible')
                         el = el.parentElement;
                     return {im, el}; })
        .filter(({el}) => el && el.tagName !== 'ARTICLE' && el.scrollWidth - el.clientWidth > 2)
        .map(({im, el}) => ({name: (im.alt || '').slice(0, 50), caption: !!el.querySelector('figcaption'),
                             faded: el.scrollLeft < 1 && el.classList.contains('pinnhjb-more-right') &&
                                    getComputedStyle(el).maskImage !== 'none'}))
        .filter(f => f.caption || !f.faded);
}"""
    % _IS_SHOWN
)

_OVERFLOW = """() => {
    const W = innerWidth, out = [];
    for (const el of document.querySelectorAll('body *')) {
        const r = el.getBoundingClientRect();
        if (r.width === 0 || r.right <= W + 1) continue;
        let p = el.parentElement, contained = false;
        for (; p && p !== document.body; p = p.parentElement)
            if (getComputedStyle(p).overflowX !== 'visible') { contained = true; break; }
        if (contained || getComputedStyle(el).position === 'fixed') continue;
        if (el.parentElement && el.parentElement.getBoundingClientRect().right > W + 1 &&
            el.parentElement !== document.body) continue;  // report the outermost one
        out.push(el.tagName.toLowerCase() + (el.className && typeof el.className === 'string'
                 ? '.' + el.className.trim().split(/\\s+/).slice(0, 2).join('.') : '') +
                 ` (right edge ${Math.round(r.right)} px)`);
    }
    return {scroll: document.scrollingElement.scrollWidth, width: W, culprits: out.slice(0, 6)};
}"""

_CUT = (
    """() => {
    const shown = (%s), out = [];
    const name = el => el.tagName.toLowerCase() + (el.getAttribute('display') ? '[display]' : '') +
        (el.closest('.cell') ? ' in a cell' : '') + ': ' + (el.textContent || el.alt || '').trim().slice(0, 40);
    for (const el of document.querySelectorAll(
            'article mjx-container, article table, article img, article pre, article .pinnhjb-explorer')) {
        if (!shown(el)) continue;
        const r = el.getBoundingClientRect(), cs = getComputedStyle(el);
        if (el.scrollWidth > el.clientWidth + 1 && /hidden|clip/.test(cs.overflowX)) {
            out.push(name(el) + ` (hides ${el.scrollWidth - el.clientWidth} px of itself)`);
            continue;
        }
        for (let p = el.parentElement; p && p !== document.body; p = p.parentElement) {
            const ps = getComputedStyle(p);
            if (ps.overflowX === 'visible') continue;
            const pr = p.getBoundingClientRect();
            if (/hidden|clip/.test(ps.overflowX) && (r.right > pr.right + 1 || r.left < pr.left - 1))
                out.push(name(el) + ` (cut by ${p.tagName.toLowerCase()}.${String(p.className).split(' ')[0]})`);
            break;
        }
    }
    return out;
}"""
    % _IS_SHOWN
)

_SEARCH_BOXES = (
    """() => {
    const shown = (%s);
    return Array.from(document.querySelectorAll('.search-button-field, .search-button, form.bd-search'))
        .filter(el => !el.closest('dialog:not([open])') && shown(el)
                      && el.getBoundingClientRect().width > 0).map(el => el.className);
}"""
    % _IS_SHOWN
)

_NAV_LINKS = """() => Array.from(document.querySelectorAll(
        '#pst-primary-sidebar-modal a[href], .bd-sidebar-primary a[href]'))
    .filter(a => {
        const r = a.getBoundingClientRect();
        if (r.width < 1 || r.height < 1 || r.right <= 0 || r.left >= innerWidth || r.bottom <= 0 ||
            r.top >= innerHeight || getComputedStyle(a).visibility !== 'visible') return false;
        const hit = document.elementFromPoint(Math.max(0, Math.min(r.left + r.width / 2, innerWidth - 1)),
                                              r.top + r.height / 2);
        return !!hit && (hit === a || a.contains(hit));  // reachable: nothing covers it
    }).map(a => a.textContent.trim())"""

_TOC_LINKS = _NAV_LINKS.replace("#pst-primary-sidebar-modal", "#pst-secondary-sidebar-modal").replace(
    ".bd-sidebar-primary", ".bd-sidebar-secondary"
)

_LINKS = """() => Array.from(document.querySelectorAll('article.bd-article a[href]'))
    .filter(a => !a.closest('.prev-next-area, .bd-footer-article, nav'))
    .map(a => new URL(a.getAttribute('href'), location.href).pathname)"""


def _move_sliders(page, where: str, problems: list[str]) -> int:
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
        if not (len(before["shown"]) == 1 and before["width"] > 0):
            problems.append(f"{where}: explorer {k + 1} shows {before}")
            continue
        if int(before["max"]) < 1:
            problems.append(f"{where}: explorer {k + 1} has a single frame")
            continue
        ex.locator("input[type=range]").focus()
        key = "ArrowRight" if int(before["value"]) < int(before["max"]) else "ArrowLeft"
        page.keyboard.press(key)  # a real user input: fires the 'input' event the explorer listens to
        after = ex.evaluate(state)
        if after["value"] == before["value"]:
            problems.append(f"{where}: explorer {k + 1}: the slider did not move")
        elif not (
            len(after["shown"]) == 1
            and after["shown"] != before["shown"]
            and after["src"] != before["src"]
            and after["width"] > 0
        ):
            problems.append(
                f"{where}: explorer {k + 1}: moving the slider did not change the frame ({before} -> {after})"
            )
        elif after["label"] == before["label"]:
            problems.append(f"{where}: explorer {k + 1}: the value label did not change")
    return n


def _nav_links_when(page, opened: bool) -> list[str]:
    """The reachable navigation links once the drawer/sidebar is open (or closed), waiting out its transition."""
    want = f"n >= {MIN_DRAWER_LINKS}" if opened else "n === 0"
    try:
        page.wait_for_function(f"() => {{ const n = ({_NAV_LINKS})().length; return {want}; }}", timeout=5_000)
    except Exception:  # playwright's TimeoutError: report what shows
        pass
    return page.evaluate(_NAV_LINKS)


def _check_drawer(page, where: str, size: str, problems: list[str]):
    """Phone: the menu button opens the navigation drawer with reachable links, and Escape closes it.
    Desktop: the menu button hides the sidebar and shows it again."""
    buttons = page.locator("button.primary-toggle:visible")
    if buttons.count() == 0:
        problems.append(f"{where}: no visible menu (primary sidebar) button")
        return
    closed = page.evaluate(_NAV_LINKS)
    if size == "phone":
        if closed:
            problems.append(f"{where}: navigation links show before the menu button is pressed: {closed[:3]}")
        buttons.first.click()
        opened = _nav_links_when(page, opened=True)
        if len(opened) < MIN_DRAWER_LINKS:
            problems.append(
                f"{where}: pressing the menu button shows {len(opened)} navigation links "
                f"(want >= {MIN_DRAWER_LINKS}): {opened}"
            )
            return
        page.keyboard.press("Escape")
        if _nav_links_when(page, opened=False):
            problems.append(f"{where}: the navigation drawer does not close on Escape")
            return
        contents = page.locator("button.secondary-toggle:visible")  # "on this page", where a page has one
        if contents.count():
            contents.first.click()
            try:
                page.wait_for_function(f"() => ({_TOC_LINKS})().length > 0", timeout=5_000)
            except Exception:  # playwright's TimeoutError
                problems.append(f"{where}: pressing the contents button shows no link to a section of the page")
            page.keyboard.press("Escape")
    else:
        if len(closed) < MIN_DRAWER_LINKS:
            problems.append(f"{where}: the sidebar shows {len(closed)} navigation links on a desktop")
            return
        buttons.first.click()
        hidden = _nav_links_when(page, opened=False)
        buttons.first.click()
        shown = _nav_links_when(page, opened=True)
        if hidden or len(shown) < MIN_DRAWER_LINKS:
            problems.append(
                f"{where}: the menu button does not hide and show the sidebar "
                f"({len(closed)} -> {len(hidden)} -> {len(shown)} links)"
            )


def _sweep_one(v: _Visit, found: dict, theory: set[str]):
    page, where, rel, size = v.page, v.where, v.rel, v.size

    external = v.external_requests()
    if external:
        found["requests"].append(f"{where}: requests left the machine: {external[:5]}")
    n_failed = len(v.failures)
    if n_failed:
        found["requests"].append(f"{where}: failed requests: {v.failures[:5]}")

    if _wait_for_math(page):
        found["n_math"].append(where)
        m = page.evaluate(_MATH_STATE)
        if not m["n_out"] >= m["n_math"] > 0:
            found["math"].append(f"{where}: {m['n_math']} math elements but {m['n_out']} rendered by MathJax")
        if m["n_err"]:
            found["math"].append(f"{where}: MathJax reported {m['n_err']} errors")
        raw = re.findall(r"\$\$|\\\(|\\\)|\\\[|\\\]|\\begin\{", m["text"])
        if raw:
            found["math"].append(f"{where}: raw TeX left visible: {raw[:5]}")

    broken = page.evaluate(_IMAGES_BROKEN)
    if broken:
        found["images"].append(f"{where}: {len(broken)} images did not load: {broken[:3]}")
    if WIDGET_VIEW_MARK in page.content():
        found["images"].append(f"{where}: a widget view needs the ipywidgets manager, which the site does not load")

    for box in page.evaluate(_FIGURE_BOXES):
        why = "scrolls with its caption" if box["caption"] else "does not fade at the edge with more"
        found["figures"].append(f"{where}: the box of '{box['name']}' scrolls sideways but {why}")
    for fig in page.evaluate(_FIGURES):
        if fig["height"] > 0 and fig["nh"] > 0:
            aspect, natural = fig["shown"] / fig["height"], fig["nw"] / fig["nh"]
            if abs(aspect / natural - 1) > 0.03:
                found["aspect"].append(
                    f"{where}: '{fig['name']}' is drawn at aspect {aspect:.2f}, its image has {natural:.2f}"
                )
        if fig["shown"] < MIN_FIGURE_SCALE * fig["intended"]:
            kind = "explorer frame" if fig["explorer"] else "figure"
            found["figures"].append(
                f"{where}: {kind} '{fig['name']}' shows at {fig['shown']:.0f} of {fig['intended']:.0f} px "
                f"({fig['shown'] / fig['intended']:.2f}x; natural width {fig['nw']} px)"
            )

    for c in page.evaluate(_CODE_SCROLLING):
        found["code"].append(
            f"{where}: {c['where']} scrolls {c['over']} px in a {c['width']} px box; "
            f"longest line ({c['chars']} chars): {c['line']!r}"
        )
    if size == "desktop" or (size == "laptop" and rel.startswith("notebooks/")):
        for c in page.evaluate(_CODE_WRAPPED):
            found["code"].append(
                f"{where}: {c['where']} wraps in a {c['width']} px box: a line too long for the column "
                f"({c['chars']} chars): {c['line']!r}"
            )

    for c in page.evaluate(_CODE_NOT_HANGING):
        found["code"].append(
            f"{where}: {c['where']} wraps back to the left of where its code starts"
            + (f" (by {c['by']} px)" if "by" in c else "")
            + f": {c['line']!r}"
        )

    for c in page.evaluate(_EQUATIONS_SCROLLING):
        kind = "an inline formula" if c["inline"] else f"a display equation at font size {c['size'] or 'as drawn'}"
        found["equations"].append(f"{where}: {kind} scrolls {c['over']} px in a {c['width']} px box: {c['text']!r}")
    loose = page.evaluate(_LOOSE_PUNCTUATION)
    if loose:
        found["equations"].append(
            f"{where}: {len(loose)} inline formulas not glued to the punctuation around them: {loose[:3]}"
        )
    idle = page.evaluate(_IDLE_SHADOWS)
    if idle:
        found["equations"].append(f"{where}: {len(idle)} boxes that fit draw scroll shadows: {idle[:3]}")

    for c in page.evaluate(_OUTPUT_SCROLLING):
        found["outputs"].append(
            f"{where}: the output of {c['where']} scrolls {c['over']} px in a {c['width']} px box: {c['line']!r}"
        )

    text = page.evaluate(_VISIBLE_TEXT)
    for label, pattern in RAW_LABEL_PATTERNS.items():
        hits = sorted(set(pattern.findall(text["prose"]) + pattern.findall(text["outputs"])))
        if hits:
            found["labels"].append(f"{where}: {label}: {hits[:6]}")
    keys = sorted(set(ROLE_KEY.findall(text["prose"])))
    if keys:
        found["labels"].append(f"{where}: an unresolved citation key or label in brackets: {keys[:6]}")

    if size == "desktop" and rel.startswith("notebooks/"):
        targets = {unquote(p) for p in page.evaluate(_LINKS)}
        if not any(t.endswith("/" + theory_page) for t in targets for theory_page in theory):
            found["theory_links"].append(f"{rel}: no link to a theory page ({', '.join(sorted(theory))})")

    over = page.evaluate(_OVERFLOW)
    if over["scroll"] > over["width"] + 1:
        found["overflow"].append(
            f"{where}: the page is {over['scroll']} px wide in a {over['width']} px window; "
            f"sticking out: {over['culprits']}"
        )
    for c in page.evaluate(_CUT):
        found["cut"].append(f"{where}: {c}")

    boxes = page.evaluate(_SEARCH_BOXES)
    if len(boxes) > 1 or (size == "desktop" and len(boxes) != 1):
        found["search"].append(f"{where}: {len(boxes)} search boxes/buttons show: {boxes}")

    if size == "desktop":
        n = _move_sliders(page, where, found["sliders"])
        if n:
            found["n_sliders"].append(where)
            page.evaluate("() => window.scrollTo(0, 0)")

    _full_page_shot(page, SHOTS / _shot_name(rel, size))
    found["shots"].append(_shot_name(rel, size))

    _check_drawer(page, where, size, found["drawer"])

    if len(v.failures) > n_failed:  # anything the interaction requested
        found["requests"].append(f"{where}: failed requests after interaction: {v.failures[n_failed:][:5]}")
    if v.external_requests() != external:
        found["requests"].append(
            f"{where}: requests left the machine after interaction: {v.external_requests()[len(external) :][:5]}"
        )
    found["console"].extend(f"{where}: {e}" for e in v.errors)


@pytest.fixture(scope="module")
def sweep(server, browser):
    """Every content page at every size, once; returns {check: [problems...]} plus counters."""
    SHOTS.mkdir(parents=True, exist_ok=True)
    found: dict[str, list[str]] = defaultdict(list)
    theory = _theory_pages()
    pages = [_rel(p) for p in _content_pages()]
    for rel in pages:
        for size in SIZES:
            v = _Visit(browser, server, rel, size)
            try:
                _sweep_one(v, found, theory)
            except Exception as exc:  # a page that breaks the sweep is a problem of its own, not a crash
                found["sweep"].append(f"{v.where}: {type(exc).__name__}: {exc}".splitlines()[0][:300])
            finally:
                v.close()
    found["pages"] = pages
    return found


def _report(found, key: str, what: str):
    problems = found.get(key, [])
    assert not problems, f"{what}: {len(problems)} problems\n  " + "\n  ".join(problems)


# --- static checks of the built files -----------------------------------------------------------------------


def test_site_built_and_has_explorers():
    if not (SITE / "index.html").is_file():
        _missing(f"no built site at {SITE} (run: bash scripts/build_book.sh)")
    pages = _content_pages()
    assert any(p.relative_to(SITE).parts[0] == "notebooks" and _has_explorer(_rel(p)) for p in pages), (
        "no page with an explorer slider in the built site"
    )
    for p in pages:  # the offline site references no CDN in any page
        html = p.read_text(encoding="utf-8")
        ext = re.findall(r'<(?:script|link|img|iframe)[^>]+(?:src|href)="(https?://[^"]+)"', html)
        assert not ext, f"{p.relative_to(SITE)} loads assets from the network: {ext}"
        assert WIDGET_STATE_MARK not in html, f"{p.relative_to(SITE)} embeds ipywidgets state that nothing reads"


def test_site_has_what_readers_expect():
    """A repository link on every page, a download of each chapter's notebook, no link to an empty index, and
    every image described for a reader who cannot see it (an alt text that is not its file name)."""
    if not (SITE / "index.html").is_file():
        _missing(f"no built site at {SITE} (run: bash scripts/build_book.sh)")
    import yaml

    config = yaml.safe_load((ROOT / "_config.yml").read_text(encoding="utf-8"))
    repo = (config.get("repository") or {}).get("url")
    assert repo, "_config.yml names no repository.url"
    problems = []
    genindex = SITE / "genindex.html"
    index_empty = genindex.is_file() and 'class="indextable' not in genindex.read_text(encoding="utf-8")
    for p in _content_pages():
        rel, html = _rel(p), p.read_text(encoding="utf-8")
        if f'href="{repo}"' not in html:
            problems.append(f"{rel}: no link to the repository {repo}")
        for img in re.findall(r"<img\b[^>]*>", html):
            alt = re.search(r'\balt="([^"]*)"', img)
            if not alt or not alt.group(1).strip() or re.search(r"\.(png|svg|jpe?g|gif)$", alt.group(1)):
                src = re.search(r'\bsrc="([^"]{0,60})', img)
                problems.append(f"{rel}: an image without alt text ({src.group(1) if src else img[:60]})")
        if (not genindex.is_file() or index_empty) and re.search(r'href="[^"]*genindex\.html"', html):
            problems.append(f"{rel}: links to an index page that is {'empty' if index_empty else 'missing'}")
        if rel.startswith("notebooks/"):
            source = f"_sources/{rel.removesuffix('.html')}.ipynb"
            if f'{source}"' not in html:
                problems.append(f"{rel}: no download button for {source}")
            elif not (SITE / source).is_file():
                problems.append(f"{rel}: the download {source} is missing from the site")
    get_code = SITE / "book" / "run_it_yourself.html"
    text = re.sub(r"<[^>]+>", "", get_code.read_text(encoding="utf-8")) if get_code.is_file() else ""
    if f"git clone {repo}" not in text:
        problems.append(f"book/run_it_yourself.html: no 'git clone {repo}' (the repository.url of _config.yml)")
    assert not problems, "\n  ".join(["what readers expect:"] + problems)


# --- the browser sweep --------------------------------------------------------------------------------------


def test_every_page_swept(sweep):
    _report(sweep, "sweep", "pages that broke the sweep")
    assert any(p.startswith("notebooks/") for p in sweep["pages"]) and any(
        p.startswith("book/") for p in sweep["pages"]
    )


def test_math_rendered(sweep):
    assert sweep["n_math"], "no page with math was checked"
    _report(sweep, "math", "math not rendered")


def test_requests_stay_on_the_machine(sweep):
    _report(sweep, "requests", "requests that left the machine or failed")


def test_images_load(sweep):
    _report(sweep, "images", "images that did not load")


def test_sliders_move(sweep):
    assert sweep["n_sliders"], "no explorer slider was moved"
    _report(sweep, "sliders", "explorer sliders")


def test_no_console_errors(sweep):
    _report(sweep, "console", "console errors")


def test_navigation_drawer_opens(sweep):
    _report(sweep, "drawer", "navigation (phone menu and contents drawers, desktop menu button)")


def test_one_search_box(sweep):
    _report(sweep, "search", "search boxes")


def test_no_horizontal_page_overflow(sweep):
    _report(sweep, "overflow", "pages wider than the window")


def test_wide_content_scrolls_in_its_own_box(sweep):
    _report(sweep, "cut", "equations, tables, figures or code cut off by a box that does not scroll")


def test_figures_keep_their_aspect_ratio(sweep):
    _report(sweep, "aspect", "figures drawn out of proportion")


def test_screenshots_of_every_page(sweep):
    missing = [
        f"{rel} [{size}]" for rel in sweep["pages"] for size in SIZES if not (SHOTS / _shot_name(rel, size)).is_file()
    ]
    assert not missing, f"no screenshot under {SHOTS} for: {missing}"


def test_code_fits_without_scrolling(sweep):
    _report(sweep, "code", "code input blocks that scroll sideways, or wrap on the desktop (a chapter's on a laptop)")


def test_equations_fit_their_column(sweep):
    _report(sweep, "equations", "equations that scroll sideways (write them on more lines, or as displays)")


def test_printed_outputs_wrap_in_their_box(sweep):
    _report(sweep, "outputs", "printed outputs that scroll sideways")


def test_figures_display_near_their_intended_width(sweep):
    _report(sweep, "figures", f"raster figures shown below {MIN_FIGURE_SCALE}x of their intended width")


def test_no_raw_labels_in_the_text(sweep):
    _report(sweep, "labels", "raw labels, keys or roles in the visible text")


def test_every_chapter_links_to_its_theory(sweep):
    assert _chapters(), "no chapter pages in the built site"
    _report(sweep, "theory_links", "chapters without a link to a theory page")


# --- the index redirect and the search page -----------------------------------------------------------------


def test_index_redirects_to_the_root_page(server, browser):
    v = _Visit(browser, server, "index.html", "desktop")
    try:
        assert not v.page.url.endswith("/index.html"), f"index.html did not redirect (at {v.page.url})"
        assert not v.errors, f"index.html: console errors: {v.errors}"
        assert not v.failures and not v.external_requests(), f"index.html: requests {v.failures}"
    finally:
        v.close()


def test_search_works_offline(server, browser):
    """The search page finds a word of the book with the site's own index, with no console errors."""
    v = _Visit(browser, server, "search.html?q=Riccati", "desktop")
    try:
        v.page.wait_for_function("() => document.querySelectorAll('#search-results li').length > 0", timeout=30_000)
        assert not v.errors, f"search.html: console errors: {v.errors}"
        assert not v.external_requests(), f"search.html: requests left the machine: {v.external_requests()}"
    finally:
        v.close()
