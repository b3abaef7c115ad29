// The pinnhjb book, once MathJax has typeset the page (it typesets after the page has loaded), and again when
// the window is resized:
// * an inline formula wider than its line gets the class pinnhjb-wide, which lets it scroll sideways
//   (pinnhjb.css) instead of being clipped; the others stay exactly as the theme draws them;
// * a display equation wider than its column (on a phone, most of the theory's) is drawn smaller until it fits,
//   down to FLOOR of its size; one that needs more still scrolls sideways in its box (pinnhjb.css).
//   MathJax's CHTML output is sized in em, so its font size scales the whole equation, number included;
// * a block of code wider than its box gets the class pinnhjb-wrap, which wraps its long lines (pinnhjb.css)
//   instead of making the reader scroll sideways: the chapters keep their visible code within 77 characters,
//   which fit the column from 1280 px up, but not a phone's, nor that of a window 1200 to 1280 px wide (both
//   sidebars show from 1200 px). Printed outputs always wrap (pinnhjb.css). A hidden cell's code is measured
//   again when it is opened;
// * a block of code that wraps (above; on a phone, pinnhjb.css wraps them all) is marked pinnhjb-wrap too, and
//   each line of a block of code becomes a span.pinnhjb-line that knows its indentation, so that where the
//   block wraps the rest of a long line hangs right of where the line's code starts (pinnhjb.css), instead of
//   going back to the left edge, where it would read as a line of its own at the outermost level of Python's
//   indentation. A line's indentation goes in a span.pinnhjb-lead, which a wrapped block does not break after
//   (else a long first word would leave a row of blanks) and draws at most MAX_INDENT characters wide (a
//   continuation aligned under a bracket would fill a phone's row). The text is unchanged, and so is what the
//   copy button copies;
// * an inline formula followed by punctuation (".", ",", ";", ":", ")", ...) is glued to it, so that a line never
//   starts with the full stop of the sentence before: the browser may break a line after an inline box such as
//   MathJax's formula, and before the punctuation after it. An opening bracket before it is glued too, so that no
//   line ends with "(";
// * a display equation or table that still scrolls gets the class pinnhjb-scrolls, which draws the "more this
//   way" shadows (pinnhjb.css); a box that fits draws none (drawn on every box, the shadows left a faint line at
//   the right edge of one that fits);
// * on a phone a figure is drawn wider than the column, in a box that scrolls sideways (pinnhjb.css): such a box
//   gets the class pinnhjb-more-right while more of the figure lies to its right, pinnhjb-more-left while more lies
//   to its left, and pinnhjb.css fades that edge, so the reader sees there is more to swipe to. The classes
//   follow the box as it scrolls.
(function () {
  "use strict";
  var SLACK = 2; // px: MathJax's glyphs overhang their boxes by a fraction of a pixel; that is not "wider"
  var FLOOR = 0.7; // the smallest scale of a display equation: MathJax draws at 1.27 times the text, so 0.89 of it
  var SCROLLING = 'mjx-container[jax="CHTML"][display="true"], .pst-scrollable-table-container';
  var FIGURES = "div.cell_output, figure a.image-reference, div.pinnhjb-frames"; // the boxes that may scroll a figure
  var MAX_INDENT = 16; // characters of indentation a wrapped line of code shows (a phone's line holds about 40)

  function wider(el) {
    return el.scrollWidth - el.clientWidth > SLACK;
  }

  function mark() {
    document.querySelectorAll("span.math").forEach(function (el) {
      el.classList.remove("pinnhjb-wide");
      if (wider(el)) el.classList.add("pinnhjb-wide");
    });
  }

  function fit() {
    var shown = [];
    document.querySelectorAll('mjx-container[jax="CHTML"][display="true"]').forEach(function (el) {
      if (el.dataset.pinnhjbSize === undefined) el.dataset.pinnhjbSize = el.style.fontSize || "";
      el.style.fontSize = el.dataset.pinnhjbSize; // as MathJax drew it, to measure its natural width
      if (el.clientWidth > 0) shown.push(el);
    });
    shown.forEach(function (el) {
      if (!wider(el)) return;
      var natural = el.scrollWidth, room = el.clientWidth;
      var scale = Math.max(FLOOR, (room - SLACK) / natural);
      var base = parseFloat(el.dataset.pinnhjbSize) || 100; // MathJax's own size, a percentage
      el.style.fontSize = (base * scale).toFixed(2) + "%";
    });
  }

  function wrapCode() {
    document.querySelectorAll("article pre").forEach(function (el) {
      if (el.closest(".cell_output")) return;
      el.classList.remove("pinnhjb-wrap");
      if (wider(el) || getComputedStyle(el).whiteSpace === "pre-wrap") el.classList.add("pinnhjb-wrap");
    });
  }

  function splitLines(pre) {
    // pygments writes a line's tokens as flat spans and text, and the newlines as text; a token that holds a
    // newline (a string over several lines) is split in two spans of its class
    var lines = [[]];
    Array.prototype.slice.call(pre.childNodes).forEach(function (node) {
      node.textContent.split("\n").forEach(function (piece, i) {
        if (i > 0) lines.push([]);
        if (!piece) return;
        var part = node.nodeType === Node.TEXT_NODE ? document.createTextNode(piece) : node.cloneNode(false);
        if (part.nodeType === Node.ELEMENT_NODE) part.textContent = piece;
        lines[lines.length - 1].push(part);
      });
    });
    return lines;
  }

  function lead(line, indent) {
    // the line's first indent characters (blanks, in its first nodes) moved into a span.pinnhjb-lead
    var left = indent;
    while (left > 0) {
      var first = line.firstChild, text = first.textContent, k = Math.min(left, text.length);
      if (k === text.length) line.removeChild(first);
      else first.textContent = text.slice(k);
      left -= k;
    }
    var span = document.createElement("span");
    span.className = "pinnhjb-lead";
    span.textContent = " ".repeat(indent);
    span.style.setProperty("--pinnhjb-shrink", Math.min(1, MAX_INDENT / indent).toFixed(4));
    return span;
  }

  function hang() {
    document.querySelectorAll("article div.highlight > pre").forEach(function (pre) {
      if (pre.dataset.pinnhjbLines !== undefined || pre.closest(".cell_output, .output")) return;
      var flat = Array.prototype.every.call(pre.childNodes, function (node) {
        return node.nodeType === Node.TEXT_NODE || (node.nodeType === Node.ELEMENT_NODE && !node.children.length);
      });
      pre.dataset.pinnhjbLines = "";
      if (!flat) return; // not pygments' flat tokens: left as it is
      var lines = splitLines(pre);
      pre.textContent = "";
      lines.forEach(function (parts, i) {
        var last = i === lines.length - 1;
        if (last && !parts.length) return; // the block's final newline: no line after it
        var line = document.createElement("span");
        line.className = "pinnhjb-line";
        parts.forEach(function (part) {
          line.appendChild(part);
        });
        var indent = /^ */.exec(line.textContent)[0].length;
        line.style.setProperty("--pinnhjb-indent", Math.min(indent, MAX_INDENT) + "ch");
        if (indent > 0) line.insertBefore(lead(line, indent), line.firstChild);
        pre.appendChild(line);
        if (!last) pre.appendChild(document.createTextNode("\n"));
      });
    });
  }

  function glue() {
    document.querySelectorAll("article span.math").forEach(function (el) {
      if (el.parentElement.classList.contains("pinnhjb-glue")) return;
      var next = el.nextSibling, prev = el.previousSibling;
      var after = next && next.nodeType === Node.TEXT_NODE && /^[.,;:!?)\]\u2019\u201d]+/.exec(next.textContent);
      var before = prev && prev.nodeType === Node.TEXT_NODE && /[(\[\u2018\u201c]+$/.exec(prev.textContent);
      if (!after && !before) return;
      var both = document.createElement("span");
      both.className = "pinnhjb-glue";
      el.parentNode.insertBefore(both, el);
      if (before) {
        prev.textContent = prev.textContent.slice(0, prev.textContent.length - before[0].length);
        both.appendChild(document.createTextNode(before[0]));
      }
      both.appendChild(el);
      if (after) {
        next.textContent = next.textContent.slice(after[0].length);
        both.appendChild(document.createTextNode(after[0]));
      }
    });
  }

  function shadows() {
    document.querySelectorAll(SCROLLING).forEach(function (el) {
      el.classList.toggle("pinnhjb-scrolls", wider(el));
    });
  }

  function edges(el) {
    var left = el.scrollLeft, more = el.scrollWidth - el.clientWidth;
    el.classList.toggle("pinnhjb-more-left", more > SLACK && left > SLACK);
    el.classList.toggle("pinnhjb-more-right", more > SLACK && left < more - SLACK);
  }

  function figureEdges() {
    document.querySelectorAll(FIGURES).forEach(function (el) {
      if (el.querySelector("img")) edges(el);
    });
  }

  function adjust() {
    hang();
    glue();
    mark();
    fit();
    shadows();
    wrapCode();
    figureEdges();
  }

  function whenTypeset() {
    var mj = window.MathJax;
    if (mj && mj.startup && mj.startup.promise) mj.startup.promise.then(adjust);
    else adjust();
  }

  document.addEventListener("DOMContentLoaded", hang); // needs no typesetting: before the first paint
  window.addEventListener("load", whenTypeset);
  document.addEventListener("toggle", wrapCode, true); // a hidden cell opened: <details> fires toggle
  document.addEventListener(
    "scroll",
    function (event) {
      var el = event.target;
      if (el.nodeType === Node.ELEMENT_NODE && el.matches(FIGURES)) edges(el);
    },
    true // scroll events do not bubble: listen as they go down
  );
  var timer = null;
  window.addEventListener("resize", function () {
    clearTimeout(timer);
    timer = setTimeout(adjust, 150);
  });
})();
