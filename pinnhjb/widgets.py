"""Explorers over the horizon T or the weight R: one set of precomputed frames, two renderings.

:func:`explorer` draws a figure for every value once and returns a :class:`FrameExplorer`. In a live Jupyter
kernel it is an ipywidgets slider that swaps the precomputed images (or, with ``live=True``, a continuous slider
that draws any value of the range on the fly); on the static site, where no kernel runs,
the same output carries a self-contained HTML slider (inline images and a few lines of JavaScript, no CDN),
which the book renders instead (``_config.yml`` puts ``text/html`` before the widget view).
"""

from __future__ import annotations

import base64
import hashlib
import html
import io
import struct
from collections.abc import Callable, Sequence

import matplotlib.pyplot as plt
from PIL import Image

__all__ = ["FrameExplorer", "explorer", "figure_png", "png_width"]

SCALE = 2  # frames are drawn at 2 x 100 dpi and displayed at 100 CSS px per inch: sharp on dense screens


def figure_png(fig, dpi: int = 100 * SCALE) -> bytes:
    """The PNG bytes of a matplotlib figure ``fig``, which is then closed.

    * ``fig``: the figure.
    * ``dpi``: the resolution.

    The image is stored with a palette of 256 colours (a plot has few): about a third of the bytes of full colour,
    which matters for an explorer's dozens of inline frames.
    """
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight", metadata={"Software": None})
    plt.close(fig)
    buf.seek(0)
    out = io.BytesIO()
    Image.open(buf).convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(out, "PNG", optimize=True)
    return out.getvalue()


def png_width(png: bytes) -> int:
    """The width in pixels stored in the header of the PNG bytes ``png``."""
    if png[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError("not a PNG image")
    return struct.unpack(">I", png[16:20])[0]


class FrameExplorer:
    """Precomputed frames, one per value, with a live (ipywidgets) and a static (HTML and JavaScript) rendering.

    * ``frames``: one PNG (bytes) per value.
    * ``values``: the slider's values, in order.
    * ``label``, ``fmt``: the slider's name and how a value is printed.
    * ``start``: the index shown first.
    * ``alt``: what the figure shows, for readers who cannot see it (the value is appended).
    * ``scale``: the frames' pixels per CSS pixel.
    * ``draw``: value -> figure; when given, the live widget is a continuous slider over [min(values),
      max(values)] that draws each value it is released at (the static slider keeps the frames).
    """

    def __init__(
        self,
        frames: Sequence[bytes],
        values: Sequence,
        label: str = "T",
        fmt: str = "{:g}",
        start: int = 0,
        alt: str = "",
        scale: int = SCALE,
        draw: Callable[[float], plt.Figure] | None = None,
    ):
        if len(frames) != len(values) or not frames:
            raise ValueError(f"need one frame per value; got {len(frames)} frames for {len(values)} values")
        self.frames = list(frames)
        self.values = list(values)
        self.label = label
        self.fmt = fmt
        self.start = int(start)
        self.alt = alt
        self.scale = scale
        self.draw = draw

    def _labels(self) -> list[str]:
        return [self.fmt.format(v) for v in self.values]

    def widget(self):
        """An ipywidgets view: a slider and the matching image (a precomputed frame, or one drawn on the fly)."""
        import ipywidgets as w

        labels = self._labels()
        image = w.Image(
            value=self.frames[self.start], format="png", width=png_width(self.frames[self.start]) // self.scale
        )
        if self.draw is not None:
            lo, hi = float(min(self.values)), float(max(self.values))
            slider = w.FloatSlider(
                value=float(self.values[self.start]),
                min=lo,
                max=hi,
                step=(hi - lo) / 400,
                description=f"{self.label} =",
                continuous_update=False,  # one drawing per release
                readout_format=".3g",
                layout=w.Layout(width="60%"),
            )
            slider.observe(lambda change: setattr(image, "value", figure_png(self.draw(change["new"]))), names="value")
            return w.VBox([slider, image])
        slider = w.SelectionSlider(
            options=list(zip(labels, range(len(labels)))),
            value=self.start,
            description=f"{self.label} =",
            continuous_update=True,
            layout=w.Layout(width="60%"),
        )
        slider.observe(lambda change: setattr(image, "value", self.frames[change["new"]]), names="value")
        return w.VBox([slider, image])

    def html(self) -> str:
        """A self-contained HTML slider (no kernel, no network): inline PNGs swapped by a range input."""
        digest = hashlib.sha1(b"".join(self.frames)).hexdigest()[:10]  # deterministic id per content
        uid = f"pinnhjb-explorer-{digest}"
        srcs = [f"data:image/png;base64,{base64.b64encode(f).decode()}" for f in self.frames]
        labels = self._labels()
        alt = html.escape(self.alt + ", " if self.alt else "")
        imgs = "".join(
            f'<img src="{s}" data-i="{i}" width="{png_width(f) // self.scale}" '
            f'style="display:{"block" if i == self.start else "none"};max-width:100%;height:auto" '
            f'alt="{alt}{html.escape(self.label)} = {html.escape(lab)}">'
            for i, (s, f, lab) in enumerate(zip(srcs, self.frames, labels))
        )
        label_js = ",".join(f'"{html.escape(lab)}"' for lab in labels)
        return (
            f'<div class="pinnhjb-explorer" id="{uid}">'
            f'<label>{html.escape(self.label)} = <span class="pinnhjb-value">{html.escape(labels[self.start])}'
            f'</span></label> <input type="range" min="0" max="{len(srcs) - 1}" step="1" value="{self.start}" '
            f'style="width:60%" aria-label="{html.escape(self.label)}">'
            f'<div class="pinnhjb-frames">{imgs}</div>'
            f'<script>(function(){{var r=document.getElementById("{uid}");var L=[{label_js}];'
            f'var s=r.querySelector("input");s.addEventListener("input",function(){{'
            f'r.querySelectorAll(".pinnhjb-frames img").forEach(function(im){{'
            f'im.style.display=(im.dataset.i==s.value)?"block":"none";}});'
            f'r.querySelector(".pinnhjb-value").textContent=L[s.value];}});}})();</script></div>'
        )

    def _repr_mimebundle_(self, include=None, exclude=None):
        bundle = {"text/plain": f"FrameExplorer({self.label}: {', '.join(self._labels())})", "text/html": self.html()}
        try:
            w = self.widget()
        except ImportError:  # no ipywidgets: the static slider still works in any browser
            return bundle
        widget_bundle = w._repr_mimebundle_() or {}
        bundle.update({k: v for k, v in widget_bundle.items() if k != "text/plain"})
        return bundle


def explorer(
    draw: Callable[[object], plt.Figure],
    values: Sequence,
    label: str = "T",
    fmt: str = "{:g}",
    start: int = 0,
    alt: str = "",
    live: bool = False,
) -> FrameExplorer:
    """Draw every frame once and return a :class:`FrameExplorer` over them.

    * ``draw``: value -> matplotlib figure (closed once rendered); give every frame the same axis limits when
      the frames are to be compared.
    * ``values``: the slider's values, in order.
    * ``label``, ``fmt``: the slider's name and how a value is printed.
    * ``start``: the index shown first.
    * ``alt``: what the figure shows, for readers who cannot see it (the value is appended).
    * ``live``: in a live kernel, a continuous slider over the values' range that calls ``draw`` at each value it
      is released at (``draw`` must accept any value in the range); the static site keeps the frames.
    """
    frames = [figure_png(draw(v)) for v in values]
    return FrameExplorer(frames, values, label, fmt, start, alt, draw=draw if live else None)
