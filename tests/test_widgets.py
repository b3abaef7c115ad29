"""The frame explorer: one set of frames, a live widget and a kernel-free HTML slider."""

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402

from pinnhjb import widgets  # noqa: E402


def draw(T):
    fig, ax = plt.subplots(figsize=(2, 1.5))
    ax.plot([0, 1], [0, T])
    return fig


def test_static_html_has_one_image_per_value_and_is_deterministic():
    ex = widgets.explorer(draw, [1.0, 2.0, 4.0], label="T", start=1)
    html = ex.html()
    assert html.count("<img ") == 3 and 'type="range"' in html and 'max="2"' in html
    assert "http" not in html  # nothing fetched from the network
    assert widgets.explorer(draw, [1.0, 2.0, 4.0], label="T", start=1).html() == html


def test_live_widget_swaps_precomputed_frames():
    ex = widgets.explorer(draw, [1.0, 2.0], label="T")
    box = ex.widget()
    slider, image = box.children
    assert image.value == ex.frames[0]
    slider.value = 1
    assert image.value == ex.frames[1]


def test_mimebundle_offers_both_renderings():
    bundle = widgets.explorer(draw, [1.0, 2.0])._repr_mimebundle_()
    assert "text/html" in bundle and "application/vnd.jupyter.widget-view+json" in bundle


def test_frames_and_values_must_match():
    with pytest.raises(ValueError, match="one frame per value"):
        widgets.FrameExplorer([b"png"], [1.0, 2.0])


def test_live_widget_draws_any_value_of_the_range_on_the_fly():
    drawn = []

    def spy(T):
        drawn.append(T)
        return draw(T)

    ex = widgets.explorer(spy, [1.0, 2.0, 4.0], label="T", start=1, live=True)
    assert drawn == [1.0, 2.0, 4.0]  # the static frames
    slider, image = ex.widget().children
    assert (slider.min, slider.max, slider.value) == (1.0, 4.0, 2.0) and not slider.continuous_update
    assert image.value == ex.frames[1]
    slider.value = 2.75  # between two frames: drawn now
    assert drawn[-1] == 2.75 and image.value == widgets.figure_png(draw(2.75))
    assert ex.html().count("<img ") == 3  # the static slider keeps its frames
