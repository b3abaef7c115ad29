// The pinnhjb book: an inline formula wider than its line gets the class pinnhjb-wide, which lets it scroll
// sideways (pinnhjb.css) instead of being clipped; the others stay exactly as the theme draws them. MathJax
// typesets after the page has loaded, so this runs once it is done, and again when the window is resized.
(function () {
  "use strict";
  var SLACK = 2; // px: MathJax's glyphs overhang their boxes by a fraction of a pixel; that is not "wider"

  function mark() {
    document.querySelectorAll("span.math").forEach(function (el) {
      el.classList.remove("pinnhjb-wide");
      if (el.scrollWidth - el.clientWidth > SLACK) el.classList.add("pinnhjb-wide");
    });
  }

  function whenTypeset() {
    var mj = window.MathJax;
    if (mj && mj.startup && mj.startup.promise) mj.startup.promise.then(mark);
    else mark();
  }

  window.addEventListener("load", whenTypeset);
  var timer = null;
  window.addEventListener("resize", function () {
    clearTimeout(timer);
    timer = setTimeout(mark, 150);
  });
})();
