"""Leave the ipywidgets state out of the static pages.

A notebook executed with live widgets (the explorers of chapters 3, 4 and 6) stores every widget's state in its
metadata, and MyST-NB copies that state into the page as a
``<script type="application/vnd.jupyter.widget-state+json">`` (about 0.3 MB per page here). The static site
shows each explorer's self-contained HTML slider instead of the widget view and loads no widget manager (see
``_config.yml``), so nothing reads that state: drop it before the page is written. Live notebooks keep their
widgets.
"""

STATE_KEY = "ipywidgets_state"  # MyST-NB's key for the state script (myst_nb.core.render.render_nb_finalise)


def drop_widget_state(app, pagename, templatename, context, doctree):
    js_files = getattr(app.env, "nb_metadata", {}).get(pagename, {}).get("js_files", {})
    js_files.pop(STATE_KEY, None)


def setup(app):
    app.connect("html-page-context", drop_widget_state, priority=400)  # before MyST-NB's handler (500) adds it
    return {"parallel_read_safe": True, "parallel_write_safe": True}
