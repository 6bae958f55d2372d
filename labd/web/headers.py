"""The headers every answer of the lab's HTTP port carries, against other sites.

- Every answer: ``X-Content-Type-Options: nosniff`` (a log or a blob is never run as a
  script or a page because a browser guessed its type) and ``Referrer-Policy:
  same-origin`` (a page's address, which may name a trial or a filter, never leaves the
  lab in a Referer).
- Every page (``text/html``): a strict ``Content-Security-Policy`` (``policy``): scripts,
  styles, fonts and everything else from the lab itself only; an inline script (the
  import maps, ``/docs``' and ``/redoc``'s start-up) only with the request's nonce
  (``request.state.csp_nonce``, which ``render.page`` hands to the templates), and
  WebAssembly (roslibjs's 64-bit integers compile a small module; this lets no string
  run as JavaScript); images
  also from ``data:`` and ``blob:`` (the camera's frames, the record's thumbnails and
  textures); connections to the lab and to its bridge (``ws://`` and ``wss://`` on the
  bridge's port, where the live pages' roslibjs connects); never framed by anyone
  (``frame-ancestors 'none'``, and ``X-Frame-Options: DENY`` for older browsers); forms
  posted only to the lab.
- A page that sets its own policy keeps it: the playground's runner, a frame of the
  playground page with an opaque origin (``labd.web.playground``).
- Every other answer (JSON, files): ``default-src 'none'; frame-ancestors 'none'``, so a
  file opened in a browser runs nothing; the static files keep none (their own scripts),
  and roslibjs's may be loaded from anywhere (``Access-Control-Allow-Origin: *``), as
  the runner's opaque origin loads it.
"""

from __future__ import annotations

import secrets

from starlette.datastructures import URL, MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from labd.api.site import Site
from labd.api.state import state_of

ALWAYS = {"X-Content-Type-Options": "nosniff", "Referrer-Policy": "same-origin"}
NOT_A_PAGE = "default-src 'none'; frame-ancestors 'none'"
STATIC = "/static/"
SHARED = "/static/vendor/roslib/"  # public npm code that the playground's runner loads


def policy(nonce: str, site: Site, host: str) -> str:
    """The Content-Security-Policy of a page served to a browser that asked ``host``."""
    host = f"[{host}]" if ":" in host else host
    port = site.bridge_port if site.bridge_port is not None else 9090
    bridge = f"ws://{host}:{port} wss://{host}:{port}"
    return "; ".join(
        [
            "default-src 'self'",
            f"script-src 'self' 'nonce-{nonce}' 'wasm-unsafe-eval'",
            f"style-src 'self' 'nonce-{nonce}'",
            "img-src 'self' data: blob:",
            "font-src 'self' data:",
            f"connect-src 'self' {bridge}",
            "worker-src 'self' blob:",
            "object-src 'none'",
            "base-uri 'none'",
            "form-action 'self'",
            "frame-ancestors 'none'",
        ]
    )


class SecurityHeaders:
    """ASGI middleware: the headers of the module docstring on every HTTP answer."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        nonce = secrets.token_urlsafe(18)
        scope.setdefault("state", {})["csp_nonce"] = nonce

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in ALWAYS.items():
                    headers.setdefault(name, value)
                if headers.get("content-type", "").startswith("text/html"):
                    site = state_of(scope["app"]).site
                    host = _host(scope)
                    # a page may bring its own, stricter in its way (the playground's runner)
                    headers.setdefault("Content-Security-Policy", policy(nonce, site, host))
                    headers.setdefault("X-Frame-Options", "DENY")
                elif not scope["path"].startswith(STATIC):
                    headers.setdefault("Content-Security-Policy", NOT_A_PAGE)
                elif scope["path"].startswith(SHARED):
                    headers["Access-Control-Allow-Origin"] = "*"
            await send(message)

        await self.app(scope, receive, with_headers)


def _host(scope: Scope) -> str:
    """The host name the browser asked for (as the pages' bridge address uses it)."""
    return URL(scope=scope).hostname or "127.0.0.1"
