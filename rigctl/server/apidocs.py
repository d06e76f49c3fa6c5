"""``rigctl serve``'s OpenAPI page (``/docs``) from Swagger UI files shipped with rigctl
(``rigctl/server/static/swagger-ui``: swagger-ui-dist, Apache-2.0, unmodified; its README names the version and the
hashes), never from a CDN: the page works on an offline rig PC and loads no third party's code into the API's origin.

The page holds no token: its one inline script reads it from the page's own address (``/docs?token=...``, which the
guard already checked), fetches the Swagger UI files and ``/openapi.json`` with ``Authorization: Bearer`` (every path
stays behind the token, these included) and sends it with the requests tried from the page. Its
Content-Security-Policy allows that script (by hash), the fetched files (as ``blob:`` URLs) and requests to the server
itself, nothing else; ``Referrer-Policy: no-referrer`` keeps the address with the token from leaving the page.
"""

from __future__ import annotations

import base64
import functools
import hashlib
from importlib import resources

from fastapi import FastAPI
from fastapi.responses import HTMLResponse, Response

__all__ = ["ASSETS", "docs_page", "install_docs"]

#: the Swagger UI files served under ``/docs/``, with their media types
ASSETS = {"swagger-ui-bundle.js": "text/javascript; charset=utf-8", "swagger-ui.css": "text/css; charset=utf-8"}

_BOOT = """
(async () => {
  const token = new URLSearchParams(window.location.search).get("token") || "";
  const auth = {Authorization: "Bearer " + token};
  const get = async (path) => {
    const r = await fetch(path, {headers: auth, cache: "no-store"});
    if (!r.ok) throw new Error(path + ": " + r.status + " " + r.statusText);
    return URL.createObjectURL(await r.blob());
  };
  const [css, js] = await Promise.all([get("/docs/swagger-ui.css"), get("/docs/swagger-ui-bundle.js")]);
  const link = document.createElement("link");
  link.rel = "stylesheet";
  link.href = css;
  document.head.appendChild(link);
  const script = document.createElement("script");
  script.src = js;
  script.onload = () => {
    window.ui = SwaggerUIBundle({
      url: "/openapi.json", dom_id: "#swagger-ui", deepLinking: true,
      requestInterceptor: (request) => { request.headers.Authorization = "Bearer " + token; return request; },
    });
  };
  document.body.appendChild(script);
})().catch((error) => {
  document.getElementById("swagger-ui").textContent = "rigctl serve: the API page did not load (" + error.message + ")";
});
"""

_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>rigctl serve API</title>
</head>
<body>
<div id="swagger-ui">loading...</div>
<script>{boot}</script>
</body>
</html>
"""


def _csp() -> str:
    digest = base64.b64encode(hashlib.sha256(_BOOT.encode()).digest()).decode()
    return ("default-src 'none'; "
            f"script-src 'sha256-{digest}' blob:; "
            "style-src blob: 'unsafe-inline'; "  # Swagger UI sets style attributes
            "img-src 'self' data:; font-src data:; connect-src 'self'; "
            "base-uri 'none'; form-action 'none'; frame-ancestors 'none'")


def docs_page() -> HTMLResponse:
    """The page (no token in it), with its Content-Security-Policy and no-referrer headers."""
    return HTMLResponse(_PAGE.format(boot=_BOOT), headers={
        "Content-Security-Policy": _csp(), "Referrer-Policy": "no-referrer", "Cache-Control": "no-store",
        "X-Content-Type-Options": "nosniff"})


@functools.cache
def _asset(name: str) -> bytes:
    return resources.files("rigctl.server").joinpath("static", "swagger-ui", name).read_bytes()


def install_docs(app: FastAPI) -> None:
    """``GET /docs`` and its two Swagger UI files (``/docs/swagger-ui-bundle.js``, ``/docs/swagger-ui.css``), behind
    the app's guard like every path."""

    @app.get("/docs", include_in_schema=False)
    async def docs() -> HTMLResponse:
        """The OpenAPI page."""
        return docs_page()

    @app.get("/docs/{name}", include_in_schema=False)
    async def asset(name: str) -> Response:
        """One of :data:`ASSETS` (404 for any other name)."""
        media_type = ASSETS.get(name)
        if media_type is None:
            return Response(b'{"detail": "not found"}', status_code=404, media_type="application/json")
        return Response(_asset(name), media_type=media_type,
                        headers={"Cache-Control": "no-store", "X-Content-Type-Options": "nosniff"})
