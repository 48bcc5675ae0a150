"""Sign-in of the clinician pages: an existing clinician or admin bearer token in an HttpOnly cookie.

The cookie is ``<token>.<nonce>.<issued>.<mac>``; ``mac`` and the CSRF token are HMAC-SHA256 keyed by the bearer
token itself, so nothing is stored server-side (no schema change, any number of API processes), a revoked token
ends every page session at once, and nobody without the token can forge either value. The nonce makes each
sign-in a session of its own with its own CSRF token. Cookies are SameSite=Strict (a cross-site request never
carries them) and every POST must also carry the session's CSRF token (defence in depth). Before sign-in, the login
form is protected by a double-submit cookie.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import time
from dataclasses import dataclass

from fastapi import Request, Response
from sqlalchemy.orm import Session as DbSession

from server.auth.service import Principal
from server.ui import data

COOKIE = "gaitmon_ui"
LOGIN_COOKIE = "gaitmon_ui_login"
MAX_AGE_S = 12 * 3600  # a clinic shift; then sign in again


class SignInRequired(Exception):
    """No valid page session: the route answers with a redirect to the sign-in form."""


class CsrfRejected(Exception):
    """A POST without the session's CSRF token."""


class DeviceToken(Exception):
    """A device token: apps upload with it, it has no pages."""


@dataclass(frozen=True)
class UiUser:
    """Who is signed in to the pages, with the CSRF token of this page session."""

    principal: Principal
    csrf: str


def _mac(token: str, message: str) -> str:
    return hmac.new(token.encode(), message.encode(), hashlib.sha256).hexdigest()


def _set(response: Response, request: Request, name: str, value: str, max_age: int, path: str = "/ui") -> None:
    response.set_cookie(name, value, max_age=max_age, path=path, httponly=True, samesite="strict",
                        secure=request.url.scheme == "https")


def start(response: Response, request: Request, token: str) -> None:
    """Open a page session for this (already verified) token."""
    nonce = secrets.token_urlsafe(16)
    issued = str(int(time.time()))
    _set(response, request, COOKIE, f"{token}.{nonce}.{issued}.{_mac(token, f'session|{nonce}|{issued}')}",
         MAX_AGE_S)
    response.delete_cookie(LOGIN_COOKIE, path="/ui")


def end(response: Response, request: Request) -> None:
    """Delete the page-session cookie."""
    response.delete_cookie(COOKIE, path="/ui", httponly=True, samesite="strict",
                           secure=request.url.scheme == "https")


def current(request: Request, db: DbSession) -> UiUser:
    """The signed-in clinician or admin, or SignInRequired / DeviceToken."""
    raw = request.cookies.get(COOKIE, "")
    parts = raw.split(".")
    if len(parts) != 4:
        raise SignInRequired
    token, nonce, issued, mac = parts
    if not hmac.compare_digest(mac, _mac(token, f"session|{nonce}|{issued}")):
        raise SignInRequired
    if not issued.isdigit() or time.time() - int(issued) > MAX_AGE_S:
        raise SignInRequired
    principal = data.principal_for_token(db, token)
    if principal is None:
        raise SignInRequired
    if principal.role not in ("clinician", "admin"):
        raise DeviceToken
    return UiUser(principal, _mac(token, f"csrf|{nonce}")[:40])


def check_csrf(user: UiUser, submitted: str | None) -> None:
    """Refuse a form whose CSRF token is not the page session's own."""
    if not submitted or not hmac.compare_digest(submitted, user.csrf):
        raise CsrfRejected


def login_form_value(request: Request) -> str:
    """The double-submit value of the sign-in form (reused while its cookie lives)."""
    return request.cookies.get(LOGIN_COOKIE) or secrets.token_urlsafe(24)


def set_login_cookie(response: Response, request: Request, value: str) -> None:
    """Set the sign-in form's own token cookie (one hour)."""
    _set(response, request, LOGIN_COOKIE, value, 3600)


def check_login_form(request: Request, submitted: str | None) -> None:
    """Refuse a sign-in form that did not come from this server's form."""
    expected = request.cookies.get(LOGIN_COOKIE)
    if not expected or not submitted or not hmac.compare_digest(expected, submitted):
        raise CsrfRejected
