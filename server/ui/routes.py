"""The clinician pages under ``/ui/``: sign-in, my patients, patient, session, estimator comparison, downloads.

Every page resolves the signed-in principal from the page cookie and reads through :mod:`server.ui.data`, so the
API's access rules hold unchanged (another clinician's patient or session is a 404, also by URL). Errors are HTML
pages with the API's status code, never a stack trace.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Coroutine
from datetime import date, datetime, time
from http import HTTPStatus
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Form, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, RedirectResponse, StreamingResponse
from fastapi.routing import APIRoute
from fastapi.templating import Jinja2Templates
from pydantic import ValidationError
from sqlalchemy.orm import Session as DbSession

from server.calibrations.schemas import CalibrationIn
from server.content_disposition import attachment
from server.deps import AppSettings, get_db
from server.enums import Role
from server.errors import ProblemError
from server.trends.timeutil import zone
from server.ui import data, signin, views
from server.ui.signin import CsrfRejected, DeviceToken, SignInRequired, UiUser

log = logging.getLogger("gaitmon.ui")
HERE = Path(__file__).parent
STATIC_DIR = HERE / "static"
templates = Jinja2Templates(directory=HERE / "templates")

# Pages hold patient data: never cached, never framed, no script at all, nothing from another host.
SECURITY_HEADERS = {
    "Cache-Control": "no-store",
    "Content-Security-Policy": "default-src 'none'; style-src 'self'; img-src 'self' data:; form-action 'self'; "
                               "frame-ancestors 'none'; base-uri 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "same-origin",
    "X-Frame-Options": "DENY",
}


NOT_FOUND_DETAIL = "There is no such page, or it belongs to another clinician's patient."


def _error_page(request: Request, status: int, title: str, detail: str) -> HTMLResponse:
    return templates.TemplateResponse(request, "error.html", {"title": title, "detail": detail, "user": None},
                                      status_code=status, headers=SECURITY_HEADERS)


def page_error(request: Request, status: int, detail: str) -> HTMLResponse | None:
    """The HTML page for an error on a page address that no page route handled (an unknown address, a wrong
    method, an address holding text no database can store); None for the API's addresses (problem details)."""
    path = request.scope.get("path", "")
    if path != "/ui" and not path.startswith("/ui/"):
        return None
    if status == 404:
        return _error_page(request, 404, "Not found", NOT_FOUND_DETAIL)
    if status == 422:
        return _error_page(request, 422, "Invalid address",
                           "The address holds a character no page address can have (a NUL or a lone surrogate).")
    return _error_page(request, status, HTTPStatus(status).phrase, detail)


class PageRoute(APIRoute):
    """A route whose failures render as HTML pages (sign-in redirect, 403, 404, 422) instead of problem+json."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def run(request: Request) -> Response:
            try:
                response = await handler(request)
            except SignInRequired:
                return RedirectResponse("/ui/login", status_code=303, headers=SECURITY_HEADERS)
            except DeviceToken:
                return _error_page(request, 403, "No pages for device tokens",
                                   "This is a device token: the phone app uploads recordings with it. "
                                   "Sign in with your clinician token instead.")
            except CsrfRejected:
                return _error_page(request, 403, "Form expired",
                                   "The form was not sent from this site's current page. Reload the page and "
                                   "try again.")
            except ProblemError as exc:
                title = "Not found" if exc.status == 404 else (exc.title or "Not possible")
                detail = NOT_FOUND_DETAIL if exc.status == 404 else exc.detail
                return _error_page(request, exc.status, title, detail)
            except RequestValidationError as exc:
                bad = ", ".join(str(e.get("loc", ["?"])[-1]) for e in exc.errors())
                return _error_page(request, 422, "Invalid address", f"Check the value of: {bad}.")
            for key, value in SECURITY_HEADERS.items():
                response.headers.setdefault(key, value)
            return response

        return run


router = APIRouter(prefix="/ui", route_class=PageRoute, include_in_schema=False)
Db = Annotated[DbSession, Depends(get_db)]


def current_user(request: Request, db: Db) -> UiUser:
    """The signed-in clinician or admin of this request, or a redirect to sign-in."""
    return signin.current(request, db)


User = Annotated[UiUser, Depends(current_user)]


def page(request: Request, name: str, user: UiUser | None, **ctx: Any) -> HTMLResponse:
    """Render a template with the signed-in user in its context."""
    return templates.TemplateResponse(request, name, {"user": user, **ctx})


@router.get("", response_class=HTMLResponse)
@router.get("/", response_class=HTMLResponse)
def home() -> RedirectResponse:
    """The pages start at the patient list."""
    return RedirectResponse("/ui/patients", status_code=303)


@router.get("/login", response_class=HTMLResponse)
def login_form(request: Request) -> HTMLResponse:
    """The sign-in form, with a login-form token in a cookie of its own (CSRF on sign-in)."""
    value = signin.login_form_value(request)
    response = page(request, "login.html", None, form_token=value, error=None)
    signin.set_login_cookie(response, request, value)
    return response


@router.post("/login", response_class=HTMLResponse)
def login(request: Request, db: Db, token: Annotated[str, Form()] = "",
          form_token: Annotated[str, Form()] = "") -> Response:
    """Check the token like the API does and start a page session (clinicians and admins only)."""
    signin.check_login_form(request, form_token)
    principal = data.principal_for_token(db, token.strip()) if token.strip() else None
    error = None
    if principal is None:
        error = "This token is not valid (mistyped, or revoked). Ask your administrator for a new one."
    elif principal.role == "device":
        error = ("This is a device token: the phone app uploads recordings with it and it has no pages. "
                 "Sign in with your clinician token.")
    if error is not None:
        log.info("ui sign-in refused: %s", "device token" if principal else "invalid token")
        response = page(request, "login.html", None, form_token=form_token, error=error)
        response.status_code = 401 if principal is None else 403
        return response
    response = RedirectResponse("/ui/patients", status_code=303)
    signin.start(response, request, token.strip())
    log.info("ui sign-in of token %s (%s)", principal.token_id, principal.role)
    return response


@router.post("/logout")
def logout(request: Request, user: User, csrf: Annotated[str, Form()] = "") -> Response:
    """End the page session (POST with the CSRF token)."""
    signin.check_csrf(user, csrf)
    response = RedirectResponse("/ui/login", status_code=303)
    signin.end(response, request)
    return response


@router.get("/patients", response_class=HTMLResponse)
def patients(request: Request, db: Db, user: User, q: Annotated[str, Query(max_length=200)] = "",
             page_no: Annotated[int, Query(alias="page", ge=1, le=100_000)] = 1) -> HTMLResponse:
    """My patients: the attention list first, then every patient, searchable by external id."""
    ctx = views.patients_page(db, user.principal, search=q.strip(), page=page_no)
    return page(request, "patients.html", user, **ctx)


@router.get("/patients/{patient_id}", response_class=HTMLResponse)
def patient(request: Request, patient_id: str, db: Db, user: User, bucket: str | None = None,
            sessions_page: Annotated[int, Query(ge=1, le=100_000)] = 1,
            calibrated: Annotated[int | None, Query(ge=0, le=1_000_000)] = None) -> HTMLResponse:
    """One patient's trends per leg, symmetry, calendar, calibrations and sessions."""
    p = data.patient_for(db, user.principal, patient_id)
    return page(request, "patient.html", user, calibrated=calibrated,
                **views.patient_page(db, p, bucket=bucket, session_page=sessions_page))


@router.post("/patients/{patient_id}/calibrations")
def patient_calibration(request: Request, patient_id: str, db: Db, user: User,
                        csrf: Annotated[str, Form()] = "", leg: Annotated[str, Form()] = "",
                        standing_knee_deg: Annotated[str, Form()] = "", measured_on: Annotated[str, Form()] = "",
                        method: Annotated[str, Form()] = "goniometer") -> Response:
    """Record a knee calibration from the patient page (measured on a local date, noon in the patient's zone); the
    same validation and storage as ``POST /v1/patients/{id}/calibrations``."""
    signin.check_csrf(user, csrf)
    p = data.patient_for(db, user.principal, patient_id)
    if user.principal.role not in (Role.admin, Role.clinician):
        raise ProblemError(403, "Only clinicians and admins record calibrations", title="Not allowed")
    try:
        day = date.fromisoformat(measured_on)
        body = CalibrationIn.model_validate({
            "leg": leg, "standing_knee_deg": float(standing_knee_deg), "method": method,
            "measured_at": datetime.combine(day, time(12), tzinfo=zone(p.timezone)).isoformat()})
    except (ValueError, ValidationError):
        raise ProblemError(422, "Give the leg, the standing knee flexion in degrees (-20 to 60) and the date it was "
                                "measured.", title="Calibration not recorded") from None
    affected = data.record_calibration(db, user.principal, p, body)
    log.info("ui calibration for patient %s (%s leg) by token %s; %d session(s) to reprocess", p.id, body.leg,
             user.principal.token_id, affected)
    return RedirectResponse(f"/ui/patients/{p.id}?calibrated={affected}#cal-entry", status_code=303)


@router.get("/patients/{patient_id}/strides.csv")
def patient_csv(request: Request, patient_id: str, db: Db, user: User) -> StreamingResponse:
    """The patient's strides as a CSV download (the API's export, authorised by the page cookie)."""
    p = data.patient_for(db, user.principal, patient_id)
    db.expunge(p)
    factory = request.app.state.sessionmaker

    def body() -> Any:
        # Its own DB session: the response streams after the request's dependencies have been closed.
        with factory() as own:
            yield from data.strides_csv(own, p)

    name = f"strides-{p.external_id or p.id}.csv".replace('"', "")
    log.info("ui strides.csv of patient %s by token %s", p.id, user.principal.token_id)
    return StreamingResponse(body(), media_type="text/csv; charset=utf-8",
                             headers={"Content-Disposition": attachment(name)})


@router.get("/patients/{patient_id}/fhir.json")
def patient_fhir(patient_id: str, db: Db, user: User, settings: AppSettings) -> Response:
    """The patient's FHIR R4 Bundle as a download."""
    p = data.patient_for(db, user.principal, patient_id)
    name = f"fhir-{p.external_id or p.id}.json".replace('"', "")
    log.info("ui FHIR export of patient %s by token %s", p.id, user.principal.token_id)
    bundle = data.fhir_bundle(db, p, settings.fhir_identifier_system)
    return Response(json.dumps(bundle), media_type="application/fhir+json",
                    headers={"Content-Disposition": attachment(name)})


@router.get("/sessions/{session_id}", response_class=HTMLResponse)
def session(request: Request, session_id: str, db: Db, user: User,
            start: Annotated[float | None, Query(ge=-1e7, le=1e7)] = None,
            end: Annotated[float | None, Query(ge=-1e7, le=1e7)] = None,
            strides: str | None = None) -> HTMLResponse:
    """One session: gait cycle, the continuous knee angle with zoom, strides and status."""
    s = data.session_for(db, user.principal, session_id)
    p = data.patient_for(db, user.principal, s.patient_id)
    ctx = views.session_page(db, p, s, start=start, end=end, all_strides=strides == "all")
    return page(request, "session.html", user, **ctx)


@router.get("/sessions/{session_id}/compare", response_class=HTMLResponse)
def compare(request: Request, session_id: str, db: Db, user: User) -> HTMLResponse:
    """The estimator comparison (the pipeline runs after this request's read transaction has ended)."""
    s = data.session_for(db, user.principal, session_id)
    p = data.patient_for(db, user.principal, s.patient_id)
    db.commit()  # end the read transaction: the comparison takes seconds and needs no connection
    return page(request, "compare.html", user,
                **views.compare_page(request.app.state.sessionmaker, user.principal, p, s))
