"""``ps-lab view``: results relit, layered, in 3-D and side by side, in a browser (WebGL 2).

:func:`load_result` reads a result folder, :class:`ViewSite` turns results into the page's files,
:func:`serve` serves them on 127.0.0.1 and :func:`export_site` writes them as a static folder.
"""

from ps_lab.view.result import CHANNELS, ViewResult, load_result
from ps_lab.view.site import HOST, ViewSite, export_site, serve

__all__ = ["CHANNELS", "HOST", "ViewResult", "ViewSite", "export_site", "load_result", "serve"]
