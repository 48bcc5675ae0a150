"""HTTP endpoints of the trends view: trends, symmetry, completeness, attention list, CSV and FHIR exports."""

from __future__ import annotations

import logging
from datetime import datetime
from enum import Enum
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse, StreamingResponse

from server.auth.service import get_patient_for, require_role
from server.content_disposition import attachment
from server.deps import AppSettings, Caller, Db
from server.enums import Role, StrideActivity
from server.errors import invalid
from server.patients.models import Patient
from server.trends import exports, service
from server.trends.attention import PRESETS, attention_list, params_for
from server.trends.metrics import METRICS
from server.trends.schemas import AttentionOut, CompletenessOut, FhirBundleOut, SymmetryOut, TrendsOut
from server.trends.timeutil import parse_bound, zone

log = logging.getLogger("gaitmon.api")
# The routes return their JSON documents directly: FastAPI's jsonable_encoder would walk a year of buckets field by
# field, which costs more than computing them; every value is already a JSON type. The response models document them.
router = APIRouter(prefix="/v1", tags=["trends"])



class FhirJSONResponse(JSONResponse):
    """JSON served as FHIR's own media type."""

    media_type = "application/fhir+json"


MetricName = Enum("MetricName", {name: name for name in METRICS}, type=str)  # type: ignore[misc]
LegName = Literal["left", "right"]
BucketName = Literal["day", "week"]
SlopeMethodName = Literal["ols", "theil_sen"]
PresetName = Enum("PresetName", {name: name for name in PRESETS}, type=str)  # type: ignore[misc]

FromQ = Annotated[str | None, Query(alias="from", description="Local date YYYY-MM-DD of the patient or ISO 8601 "
                                                               "date-time (inclusive)")]
ActivityQ = Annotated[StrideActivity, Query(description="walking or running: a trend never pools the two")]
ToQ = Annotated[str | None, Query(alias="to", description="Local date (the whole day is included) or ISO 8601 "
                                                           "date-time (exclusive)")]


def _range(patient: Patient, start: str | None, end: str | None) -> tuple[datetime | None, datetime | None]:
    tz = zone(patient.timezone)
    bounds: list[datetime | None] = []
    for field, value, is_end in (("from", start, False), ("to", end, True)):
        if value is None or not value.strip():
            bounds.append(None)
            continue
        try:
            bounds.append(parse_bound(value, tz, end=is_end))
        except ValueError as exc:
            raise invalid(field, "expected a date YYYY-MM-DD or an ISO 8601 date-time") from exc
    lo, hi = bounds
    if lo is not None and hi is not None and lo >= hi:
        raise invalid("from", "must be before 'to'")
    return lo, hi


@router.get("/patients/{patient_id}/trends", response_model=TrendsOut, operation_id="getPatientTrends",
            summary="Longitudinal trend of one gait metric of one leg")
def get_trends(patient_id: str, db: Db, caller: Caller, metric: MetricName = MetricName.peak_swing_flexion_deg,
               leg: LegName | None = None, bucket: BucketName = "day", start: FromQ = None, end: ToQ = None,
               method: SlopeMethodName = "ols",
               window_days: Annotated[float, Query(ge=1, le=180)] = service.WINDOW_DAYS,
               activity: ActivityQ = StrideActivity.walking) -> JSONResponse:
    """Longitudinal trend of one metric of one leg and activity."""
    patient = get_patient_for(db, caller, patient_id)
    lo, hi = _range(patient, start, end)
    return JSONResponse(service.patient_trends(db, patient, metric_name=metric.value, leg=leg, bucket=bucket,
                                               start=lo, end=hi, method=method, window_days=window_days,
                                               activity=activity))


@router.get("/patients/{patient_id}/symmetry", response_model=SymmetryOut, operation_id="getPatientSymmetry",
            summary="Affected vs other leg per bucket (ratio, symmetry index)")
def get_symmetry(patient_id: str, db: Db, caller: Caller,
                 metric: MetricName = MetricName.peak_swing_flexion_deg, bucket: BucketName = "week",
                 start: FromQ = None, end: ToQ = None,
                 activity: ActivityQ = StrideActivity.walking) -> JSONResponse:
    """Affected vs other leg per bucket, for one activity."""
    patient = get_patient_for(db, caller, patient_id)
    lo, hi = _range(patient, start, end)
    return JSONResponse(service.patient_symmetry(db, patient, metric_name=metric.value, bucket=bucket, start=lo,
                                                 end=hi, activity=activity))


@router.get("/patients/{patient_id}/completeness", response_model=CompletenessOut,
            operation_id="getPatientCompleteness",
            summary="Remote-monitoring view: days with data, strides and walking minutes per local day")
def get_completeness(patient_id: str, db: Db, caller: Caller,
                     days: Annotated[int, Query(ge=1, le=366)] = 30,
                     activity: ActivityQ = StrideActivity.walking) -> JSONResponse:
    """Days with data, strides and minutes of one activity per local day."""
    patient = get_patient_for(db, caller, patient_id)
    return JSONResponse(service.patient_completeness(db, patient, days=days, activity=activity))


@router.get("/attention", response_model=AttentionOut, operation_id="listAttention",
            responses={400: {"description": "cursor is not a next_cursor of this API"},
                       403: {"description": "Device tokens may not see the attention list"}},
            summary="Patients who need attention (declining, stalled, silent, sensor trouble)")
def get_attention(db: Db, caller: Caller, limit: Annotated[int, Query(ge=1, le=200)] = 50,
                  cursor: str | None = None, metric: MetricName = MetricName.peak_swing_flexion_deg,
                  silent_days: Annotated[float | None, Query(gt=0, le=365)] = None,
                  stalled_weeks: Annotated[int | None, Query(ge=1, le=52)] = None,
                  window_days: Annotated[float | None, Query(ge=1, le=90)] = None,
                  preset: Annotated[PresetName, Query(description="the clinic's thresholds: named presets, "
                                                                  "echoed with every rule in `rules`")
                                    ] = PresetName.default) -> JSONResponse:
    """Patients who need attention, most severe first (the preset's thresholds unless overridden)."""
    require_role(caller, Role.admin, Role.clinician, action="see the attention list")
    offset = 0
    if cursor:
        if not cursor.isdigit():
            raise invalid("cursor", "not a cursor returned by this API", status=400)
        offset = int(cursor)
    params = params_for(preset.value, metric=metric.value, silent_days=silent_days, stalled_weeks=stalled_weeks,
                        window_days=window_days)
    return JSONResponse(attention_list(db, clinician_id=None if caller.is_admin else caller.clinician_id,
                                       params=params, limit=limit, offset=offset))


@router.get("/patients/{patient_id}/strides.csv", summary="Every stride of the patient as CSV",
            response_class=StreamingResponse, operation_id="exportStridesCsv",
            responses={200: {"description": "One row per stride, a header row first",
                             "content": {"text/csv": {"schema": {"type": "string"}}}},
                       403: {"description": "Device tokens may not export strides"}})
def get_strides_csv(patient_id: str, request: Request, db: Db, caller: Caller, start: FromQ = None,
                    end: ToQ = None, activity: ActivityQ = StrideActivity.walking) -> StreamingResponse:
    """Every stride of one activity of the patient as CSV."""
    require_role(caller, Role.admin, Role.clinician, action="export strides")
    patient = get_patient_for(db, caller, patient_id)
    lo, hi = _range(patient, start, end)
    db.expunge(patient)
    factory = request.app.state.sessionmaker

    def body() -> Any:
        # Its own DB session: the response streams after the request's dependencies have been closed.
        with factory() as own:
            yield from exports.strides_csv(own, patient, lo, hi, activity=activity)

    name = f"strides-{patient.external_id or patient.id}.csv"
    log.info("strides.csv of patient %s exported by token %s", patient.id, caller.token_id)
    return StreamingResponse(body(), media_type="text/csv; charset=utf-8",
                             headers={"Content-Disposition": attachment(name)})


@router.get("/patients/{patient_id}/fhir", response_model=FhirBundleOut, response_class=FhirJSONResponse,
            operation_id="getFhirBundle", responses={403: {"description": "Device tokens may not export FHIR"}},
            summary="Daily summaries as a FHIR R4 Bundle (collection) of Observations")
def get_fhir(patient_id: str, db: Db, caller: Caller, settings: AppSettings, start: FromQ = None, end: ToQ = None,
             activity: ActivityQ = StrideActivity.walking,
             metric: Annotated[list[MetricName] | None, Query(description="repeat to choose several")] = None,
             ) -> JSONResponse:
    """Daily summaries of one activity as a FHIR R4 Bundle of Observations."""
    require_role(caller, Role.admin, Role.clinician, action="export FHIR")
    patient = get_patient_for(db, caller, patient_id)
    lo, hi = _range(patient, start, end)
    chosen = tuple(m.value for m in metric) if metric else exports.FHIR_METRICS
    if any(METRICS[m].column is None for m in chosen):
        raise invalid("metric", "count metrics have no daily Observation; choose stride metrics")
    bundle = exports.fhir_bundle(db, patient, lo, hi, chosen, identifier_system=settings.fhir_identifier_system,
                                 activity=activity)
    return JSONResponse(bundle, media_type="application/fhir+json")
