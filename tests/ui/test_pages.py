"""The clinician pages in a real browser against a real server with simulated patients (see conftest)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

from tests.ui.conftest import REPO, SCREENSHOTS, Seeded, copy_screenshot

pytestmark = [pytest.mark.browser, pytest.mark.xdist_group("ui-browser")]


@contextmanager
def tab(browser: Any, seeded: Seeded, token: str | None = None, width: int = 1280,
        error_pages: bool = False) -> Iterator[Any]:
    """A fresh browser context (own cookies) and page; fails the test on any console error, page error or failed
    sub-resource. ``error_pages``: the test itself opens pages answered 4xx, whose console line it tolerates."""
    ctx = browser.new_context(viewport={"width": width, "height": 900}, base_url=seeded.base_url)
    page = ctx.new_page()
    errors: list[str] = []

    def on_console(m: Any) -> None:
        if m.type == "error" and not (error_pages and m.text.startswith("Failed to load resource: the server "
                                                                          "responded with a status of 4")):
            errors.append(f"console {m.type}: {m.text}")

    def on_response(r: Any) -> None:
        if r.status >= 400 and r.request.resource_type != "document":
            errors.append(f"{r.status} for {r.url}")

    page.on("console", on_console)
    page.on("response", on_response)
    page.on("pageerror", lambda e: errors.append(f"page error: {e}"))
    try:
        if token is not None:
            sign_in(page, token)
            assert page.url.endswith("/ui/patients"), page.url
        yield page
        assert errors == [], errors
    finally:
        ctx.close()


def sign_in(page: Any, token: str) -> None:
    page.goto("/ui/login")
    page.fill("#token", token)
    page.click("button[type=submit]")
    page.wait_for_load_state()


def shot(page: Any, name: str) -> None:
    page.screenshot(path=str(SCREENSHOTS / name), full_page=True)


def chart_stats(page: Any) -> list[dict[str, int]]:
    """Per inline SVG chart: its accessible name and how many drawn series/shapes it has."""
    return page.eval_on_selector_all("svg.chart", """els => els.map(e => ({
        title: e.querySelector('title') ? e.querySelector('title').textContent : '',
        labelled: e.getAttribute('aria-labelledby') ? 1 : 0,
        series: e.querySelectorAll('path.series').length,
        points: Math.max(0, ...Array.from(e.querySelectorAll('path.series'))
                         .map(p => (p.getAttribute('d').match(/[ML]/g) || []).length)),
        bands: e.querySelectorAll('polygon.band').length,
        days: e.querySelectorAll('rect.day').length,
        ticks: e.querySelectorAll('text.tk').length,
        axis_labels: e.querySelectorAll('text.al').length}))""")


def test_sign_in_and_my_patients(browser: Any, seeded: Seeded) -> None:
    with tab(browser, seeded) as page:
        page.goto("/ui/patients")
        assert page.url.endswith("/ui/login")  # not signed in: the sign-in form
        sign_in(page, seeded.clinician_a)
        assert page.url.endswith("/ui/patients")
        assert page.locator("h1").inner_text() == "My patients"
        table = page.locator("table").inner_text()
        assert "KNEE-001" in table and "KNEE-002" in table
        assert "HIP-900" not in page.content()  # another clinician's patient
        # Paul Roth's only session is 9 days old: flagged silent, in words.
        attention = page.locator("ul.attention").inner_text()
        assert "Paul Roth" in attention and "No session for 9 days" in attention
        row = page.locator("tr", has_text="KNEE-001").inner_text()
        assert "4 / 30" in row  # four days with data in the last 30
        assert "Left leg (affected):" in row and "\u00b0" in row
        shot(page, "patients.png")
        page.goto("/ui/patients?q=002")
        rows = page.locator("tbody tr").all_inner_texts()
        assert len(rows) == 1 and "KNEE-002" in rows[0]


def test_session_cookie_flags(browser: Any, seeded: Seeded) -> None:
    with tab(browser, seeded, seeded.clinician_a) as page:
        cookies = {c["name"]: c for c in page.context.cookies()}
        c = cookies["gaitmon_ui"]
        assert c["httpOnly"] is True and c["sameSite"] == "Strict" and c["path"] == "/ui"
        assert c["secure"] is False  # plain http on localhost; https sets Secure
        assert page.evaluate("document.cookie") == ""  # invisible to scripts


def test_patient_page_plots(browser: Any, seeded: Seeded) -> None:
    with tab(browser, seeded, seeded.clinician_a) as page:
        page.click("text=Anna Meier >> nth=0")
        page.wait_for_load_state()
        assert page.url.endswith(f"/ui/patients/{seeded.patient_a}")
        charts = chart_stats(page)
        titles = [c["title"] for c in charts]
        assert any(t.startswith("Days with data") for t in titles)
        for want in ("Peak knee flexion in swing", "Knee range of motion per stride",
                     "Minimum knee flexion in stance (extension deficit)", "Trustworthy strides per day"):
            chart = next(c for c in charts if c["title"] == want)
            assert chart["series"] == 2, chart  # affected leg against the other
            assert chart["points"] == 4, chart  # four days with sessions
            assert chart["ticks"] >= 6 and chart["axis_labels"] == 2 and chart["labelled"] == 1
        cal = next(c for c in charts if c["title"].startswith("Days with data"))
        assert cal["days"] >= 182
        assert any(t.startswith("Symmetry") for t in titles)
        text = page.locator("main").inner_text()
        assert "per week" in text and "95 % CI" in text
        assert "Europe/Berlin" in text
        assert page.locator("section", has_text="Sessions (4)").locator("tbody tr").count() == 4
        shot(page, "patient.png")
        page.locator("figure").first.screenshot(path=str(SCREENSHOTS / "patient-trend.png"))
        page.screenshot(path=str(SCREENSHOTS / "patient-top.png"), full_page=True,
                        clip={"x": 0, "y": 0, "width": 1280, "height": 1480})
        copy_screenshot("patient-top.png", REPO / "docs" / "ui-patient.png")
        page.click("text=Per week")
        page.wait_for_load_state()
        assert "bucket=week" in page.url and len(chart_stats(page)) == len(charts)


def test_patient_page_tablet_width(browser: Any, seeded: Seeded) -> None:
    with tab(browser, seeded, seeded.clinician_a, width=768) as page:
        page.goto(f"/ui/patients/{seeded.patient_a}")
        overflow = page.evaluate("document.documentElement.scrollWidth - document.documentElement.clientWidth")
        assert overflow <= 0, f"page is {overflow} px wider than a 768 px tablet"
        # keyboard: the first Tab lands on "Skip to content", a visible focus ring marks it
        page.keyboard.press("Tab")
        assert page.evaluate("document.activeElement.textContent") == "Skip to content"
        assert page.evaluate("getComputedStyle(document.activeElement).outlineStyle") == "solid"
        page.keyboard.press("Enter")
        assert page.evaluate("document.activeElement.id") == "main"
        shot(page, "patient-tablet.png")


def test_session_page_and_compare(browser: Any, seeded: Seeded) -> None:
    with tab(browser, seeded, seeded.clinician_a) as page:
        page.goto(f"/ui/patients/{seeded.patient_a}")
        page.locator("section", has_text="Sessions (4)").locator("tbody tr a").first.click()
        page.wait_for_load_state()
        assert page.url.endswith(f"/ui/sessions/{seeded.sessions_a[-1]}")
        charts = chart_stats(page)
        cycles = [c for c in charts if c["title"].startswith("Knee angle over the gait cycle")]
        assert len(cycles) == 2  # both legs
        for c in cycles:
            assert c["series"] == 2 and c["bands"] == 2  # this session and the first one, mean +- SD
            assert c["points"] == 101  # 0..100 % of the cycle
        trace = next(c for c in charts if c["title"] == "Knee angle, continuous")
        assert trace["series"] == 2 and trace["points"] > 100
        text = page.locator("main").inner_text()
        assert "Processed" in text and "trustworthy" in text
        n_rows = page.locator("table.strides tbody tr").count()
        assert n_rows >= 60
        shot(page, "session.png")
        page.locator("figure").first.screenshot(path=str(SCREENSHOTS / "session-cycle.png"))
        page.click("text=Zoom in \u00d72")
        page.wait_for_load_state()
        assert "start=" in page.url
        zoomed = next(c for c in chart_stats(page) if c["title"] == "Knee angle, continuous")
        assert zoomed["series"] == 2
        page.locator("table.strides tbody tr a").nth(3).click()  # one stride in the trace
        page.wait_for_load_state()
        assert "start=" in page.url and chart_stats(page)
        page.goto(f"/ui/sessions/{seeded.sessions_a[-1]}")
        page.click("text=Compare estimators")
        page.wait_for_load_state()
        assert page.locator("h1").inner_text() == "Estimator comparison"
        body = page.locator("main").inner_text()
        assert "gyroscope-only" in body and "RMS difference" in body
        assert page.locator("table").count() == 4  # per leg: the metric table and the pairwise differences
        shot(page, "compare.png")


def test_first_session_has_no_reference(browser: Any, seeded: Seeded) -> None:
    with tab(browser, seeded, seeded.clinician_a) as page:
        page.goto(f"/ui/sessions/{seeded.sessions_a[0]}")
        assert "This is the patient's first processed session" in page.locator("main").inner_text()
        cycles = [c for c in chart_stats(page) if c["title"].startswith("Knee angle over the gait cycle")]
        assert cycles and all(c["series"] == 1 for c in cycles)


def test_downloads_with_the_cookie(browser: Any, seeded: Seeded) -> None:
    with tab(browser, seeded, seeded.clinician_a) as page:
        csv = page.context.request.get(f"/ui/patients/{seeded.patient_a}/strides.csv")
        assert csv.status == 200 and csv.headers["content-type"].startswith("text/csv")
        lines = csv.text().splitlines()
        assert lines[0].startswith("session_id,client_session_id,leg,index") and len(lines) > 200
        fhir = page.context.request.get(f"/ui/patients/{seeded.patient_a}/fhir.json")
        bundle = json.loads(fhir.text())
        assert fhir.status == 200 and bundle["resourceType"] == "Bundle" and len(bundle["entry"]) >= 8


def test_device_token_gets_no_pages(browser: Any, seeded: Seeded) -> None:
    with tab(browser, seeded, error_pages=True) as page:
        sign_in(page, seeded.device)
        assert "/ui/login" in page.url
        assert "device token" in page.locator("[role=alert]").inner_text()
        assert not [c for c in page.context.cookies() if c["name"] == "gaitmon_ui"]
        page.goto(f"/ui/patients/{seeded.patient_a}")
        assert page.url.endswith("/ui/login")
        sign_in(page, "gm_not-a-token")
        assert "not valid" in page.locator("[role=alert]").inner_text()


def test_other_clinicians_patient_is_invisible(browser: Any, seeded: Seeded) -> None:
    with tab(browser, seeded, seeded.clinician_b, error_pages=True) as page:
        assert "KNEE-001" not in page.content() and "HIP-900" in page.content()
        for url in (f"/ui/patients/{seeded.patient_a}", f"/ui/sessions/{seeded.sessions_a[0]}",
                    f"/ui/sessions/{seeded.sessions_a[0]}/compare"):
            resp = page.goto(url)
            assert resp.status == 404, url
            assert "Not found" in page.locator("h1").inner_text()
            assert "Anna" not in page.content()
        shot(page, "not-found.png")
        for url in (f"/ui/patients/{seeded.patient_a}/strides.csv", f"/ui/patients/{seeded.patient_a}/fhir.json"):
            assert page.context.request.get(url).status == 404, url
    with tab(browser, seeded, seeded.admin) as page:  # an admin sees every patient, as in the API
        assert page.goto(f"/ui/patients/{seeded.patient_b}").status == 200


def test_csrf_and_sign_out(browser: Any, seeded: Seeded) -> None:
    with tab(browser, seeded, seeded.clinician_a) as page:
        req = page.context.request
        for form in ({}, {"csrf": "forged"}):
            r = req.post("/ui/logout", form=form, max_redirects=0)
            assert r.status == 403, form
        assert page.goto("/ui/patients").url.endswith("/ui/patients")  # still signed in
        r = req.post("/ui/login", form={"token": seeded.clinician_a}, max_redirects=0)
        assert r.status == 403  # sign-in form without its double-submit value
        page.click("text=Sign out")
        page.wait_for_load_state()
        assert page.url.endswith("/ui/login")
        assert not [c for c in page.context.cookies() if c["name"] == "gaitmon_ui"]
        page.goto("/ui/patients")
        assert page.url.endswith("/ui/login")
        shot(page, "login.png")
