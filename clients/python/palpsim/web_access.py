"""Who may open palpsim-web's station: loopback or not, its TLS context, the station
token and the login that trades it for a cookie (palpsim/web.py serves the rest).

Beyond loopback the gateway needs TLS and a station token; the page asks for the token
once and the cookie then holds a random login, never the token.
"""

from __future__ import annotations

import argparse
import hmac
import ipaddress
import secrets
import ssl
from pathlib import Path

MAX_FORM_BYTES = 4096          # the login form
LOOPBACK_NAMES = ("localhost",)
COOKIE = "palpsim_web"

_LOGIN_HTML = """<!doctype html><html><head><meta charset="utf-8"><title>palpsim station login</title></head>
<body style="font-family: sans-serif; margin: 3em"><h1>palpsim station</h1>{note}
<form method="post" action="/login"><label>Station token <input type="password" name="token" autofocus></label>
<button type="submit">Log in</button></form></body></html>"""


def is_loopback(host: str) -> bool:
    """True for localhost and loopback addresses."""
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_exposure(args: argparse.Namespace) -> str | None:
    """Why the gateway may not start as asked (None when it may): beyond loopback it needs
    TLS and a station token; a certificate needs its key."""
    if bool(args.tls_cert) != bool(args.tls_key):
        return "--tls-cert and --tls-key go together"
    if not is_loopback(args.host):
        missing = [n for n, v in (("--tls-cert", args.tls_cert), ("--tls-key", args.tls_key),
                                  ("--station-token-file", args.station_token_file)) if not v]
        if missing:
            return (f"--host {args.host} serves beyond loopback, which needs TLS and a station login: "
                    f"give {', '.join(missing)} (or serve on 127.0.0.1 and reach it through an SSH tunnel)")
    return None


def read_token(path: str) -> str:
    """The station token: the first line of the file, at least 16 characters."""
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as e:
        raise ValueError(f"{path}: cannot read the station token: {e.strerror}") from None
    token = lines[0].strip() if lines else ""
    if len(token) < 16:
        raise ValueError(f"{path}: the station token on its first line has {len(token)} characters, "
                         "at least 16 are needed (e.g. python3 -c 'import secrets; print(secrets.token_urlsafe())')")
    return token


def tls_context(args: argparse.Namespace) -> ssl.SSLContext | None:
    """The server's TLS context from --tls-cert and --tls-key (None without them); raises
    OSError or ssl.SSLError when they cannot be read."""
    if not args.tls_cert:
        return None
    tls = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    tls.load_cert_chain(args.tls_cert, args.tls_key)
    return tls


class StationLogin:
    """The station's login: its page, the form that checks the token, and the random
    logins (cookies) it has handed out. Without a token every request is logged in."""

    def __init__(self, prog: str, token: str | None, secure: bool):
        self.prog = prog
        self.token = token
        self.secure = secure            # the cookie only travels over TLS
        self.logins: set[str] = set()

    def logged_in(self, request) -> bool:
        """Whether the request carries a login this station handed out."""
        return self.token is None or request.cookies.get(COOKIE, "") in self.logins

    async def page(self, request):
        """GET /login: the form asking for the station token."""
        from aiohttp import web

        return web.Response(text=_LOGIN_HTML.format(note=""), content_type="text/html")

    async def login(self, request):
        """POST /login: a right token gets a new login cookie and goes to the page."""
        from aiohttp import web

        if self.token is None:
            raise web.HTTPFound("/")
        try:
            form = await request.post()
        except web.HTTPRequestEntityTooLarge:
            raise web.HTTPRequestEntityTooLarge(max_size=MAX_FORM_BYTES, actual_size=request.content_length,
                                                text=f"{self.prog}: the login form is larger than "
                                                     f"{MAX_FORM_BYTES} bytes") from None
        given = form.get("token", "")
        if not isinstance(given, str) or not hmac.compare_digest(given.encode(), self.token.encode()):
            return web.Response(status=403, content_type="text/html",
                                text=_LOGIN_HTML.format(note="<p>That is not this station's token.</p>"))
        login = secrets.token_hex(32)
        self.logins.add(login)
        resp = web.HTTPFound("/")
        resp.set_cookie(COOKIE, login, httponly=True, samesite="Strict", secure=self.secure)
        raise resp
