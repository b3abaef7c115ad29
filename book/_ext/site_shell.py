"""Fixes to the site shell (Sphinx 7.4 + sphinx-book-theme 1.3.0 + pydata-sphinx-theme 0.17.1) that need code.

1. **One copy of every inline script.** An extension that calls ``app.add_js_file(None, body=...)`` after the
   HTML builder is initialised (sphinx-thebe at ``env-before-read-docs``, sphinx-togglebutton at
   ``builder-inited``) gets its script into every page twice: Sphinx 7.4 records it once with the file name
   ``None`` and adds it again from the registry, at ``prepare_writing``, as ``''``; the two compare unequal, so
   both are written. sphinx-thebe's body declares ``const THEBE_JS_URL``, and the second copy throws
   "Identifier 'THEBE_JS_URL' has already been declared" on every page. We keep the first copy of each script.
2. **Theme defaults that make the navigation work** (see ``_config.yml``): pydata-sphinx-theme 0.17.1 fills in
   ``navbar_persistent = ["search-button-field"]`` when the user has not set it, which overrides
   sphinx-book-theme's empty header. The header it then renders holds a second search box and its own
   (hidden) ``.primary-toggle`` / ``.secondary-toggle`` buttons *before* sphinx-book-theme's visible ones, and
   both themes' scripts bind only ``document.querySelector(".primary-toggle")``, the first, hidden one: the
   visible menu and contents buttons get no handler, so on a phone the drawer never opens and on a desktop the
   menu button does nothing (pydata-sphinx-theme issue #2451). ``navbar_persistent: []`` (set in
   ``_config.yml``) removes that header; this extension checks that it stays set, so a config change cannot
   bring the bug back silently.
"""

from sphinx.errors import ConfigError


def _keep_first_copy(app, pagename, templatename, context, doctree):
    scripts = context.get("script_files")
    if not scripts:
        return
    seen, kept = set(), []
    for js in scripts:
        attrs = getattr(js, "attributes", {})
        key = (getattr(js, "filename", js) or "", getattr(js, "priority", 0), tuple(sorted(attrs.items())))
        if key not in seen:
            seen.add(key)
            kept.append(js)
    scripts[:] = kept  # the builder's own list: Sphinx restores it after each page


def _check_theme_options(app):
    opts = app.config.html_theme_options or {}
    if opts.get("navbar_persistent", None) != []:
        raise ConfigError(
            "html_theme_options.navbar_persistent must be [] (see book/_ext/site_shell.py): "
            "otherwise the phone's navigation drawer never opens"
        )


def setup(app):
    app.connect("builder-inited", _check_theme_options, priority=100)  # before the theme fills in defaults
    app.connect("html-page-context", _keep_first_copy, priority=900)  # after every page-specific script
    return {"parallel_read_safe": True, "parallel_write_safe": True}
