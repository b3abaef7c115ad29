"""Load MathJax on every page, not only on pages whose body has math.

The navigation sidebar shows chapter titles on every page, and some titles hold math (e.g. chapter 3's
"$V_T(\\cdot,0)\\to V^\\star$"): without MathJax such a page shows the raw TeX in its sidebar. MathJax is served
locally (``book/_vendor``), so loading it everywhere costs no network.
"""


def setup(app):
    app.set_html_assets_policy("always")
    return {"parallel_read_safe": True, "parallel_write_safe": True}
