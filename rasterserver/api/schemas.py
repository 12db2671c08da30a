"""Request and response bodies of the HTTP API (pydantic models, published in OpenAPI)."""

from __future__ import annotations

import datetime as dt
import json
from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, Field, PlainValidator

from rasterserver.api.fields import AccountKind, AcquisitionKind, Day, FrameRole, Instant, Role, Sex
from rasterserver.documents import CalibrationDocument, RasterDocument
from rasterserver.times import TIME_RULE


def _finite_json(document: dict[str, Any]) -> dict[str, Any]:
    """Refuse NaN and infinities: they are not JSON and break the canonical checksums."""
    try:
        json.dumps(document, allow_nan=False)
    except ValueError:
        # a ValueError becomes an ordinary 422 validation error naming the field
        raise ValueError("numbers must be finite (no NaN or Infinity)") from None
    return document


JsonObject = Annotated[dict[str, Any], AfterValidator(_finite_json)]


def _json_object(value: Any) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise ValueError("must be a JSON object")
    return value


# The documents are checked where they are stored (rasterserver.documents, through the
# archive), the same for the CLI and HTTP, with messages naming the field; here they are only
# objects, published in OpenAPI with the documents' schema.
CalibrationJson = Annotated[
    dict[str, Any], PlainValidator(_json_object, json_schema_input_type=CalibrationDocument)
]
RasterJson = Annotated[
    dict[str, Any], PlainValidator(_json_object, json_schema_input_type=RasterDocument)
]


class Health(BaseModel):
    status: str
    version: str
    schema_revision: str | None


class AccountIn(BaseModel):
    name: str = Field(min_length=1, max_length=100)
    role: Role
    kind: AccountKind = Field("user", description="A person (user) or a machine (service).")


class AccountOut(BaseModel):
    name: str
    role: Role
    kind: AccountKind


class StationIn(BaseModel):
    name: str = Field(min_length=1, max_length=100)
    description: str = ""


#: Times of stations, calibrations and rasters are withheld from researchers: when a
#: calibration applied bounds when the acquisitions made with it were taken, and so the
#: patients' date shifts.
_WITHHELD = "Null for researchers: it would bound their patients' true dates."


class StationOut(BaseModel):
    name: str
    description: str
    created_at: dt.datetime | None = Field(description=_WITHHELD)


class RasterIn(BaseModel):
    name: str = Field(min_length=1, max_length=100)
    definition: RasterJson = Field(description="A rasterserver.raster/1 document (checked).")


class RasterOut(BaseModel):
    name: str
    sha256: str
    definition: dict[str, Any]
    created_at: dt.datetime | None = Field(description=_WITHHELD)


class CalibrationIn(BaseModel):
    parameters: CalibrationJson = Field(
        description="A rasterserver.calibration/1 document (checked).")
    residuals: JsonObject | None = None
    raster: str | None = None
    valid_from: Instant | None = Field(None, description=f"From when it applies: {TIME_RULE}.")
    source_acquisition: str | None = None
    notes: str = ""


class CalibrationOut(BaseModel):
    station: str
    version: int
    sha256: str
    raster_id: int | None
    parameters: dict[str, Any]
    residuals: dict[str, Any]
    valid_from: dt.datetime | None = Field(description=_WITHHELD)
    notes: str | None = Field(description="Null for researchers (free text, may hold dates).")
    created_at: dt.datetime | None = Field(description=_WITHHELD)


class PatientIn(BaseModel):
    identifier: str = Field(min_length=1, max_length=64)
    name: str = Field("", max_length=200)
    birth_date: Day | None = Field(None, description="YYYY-MM-DD.")
    sex: Sex = "unknown"


class PatientOut(BaseModel):
    id: str = Field(description="Site identifier, or a pseudonym for researchers.")
    pseudonymised: bool
    name: str | None = Field(None, description="Absent for researchers.")
    birth_date: dt.date | None = Field(None, description="Absent for researchers.")
    sex: Sex
    created_at: dt.datetime


class VisitOut(BaseModel):
    visit_date: dt.date = Field(description="Shifted per patient for researchers.")
    notes: str | None


class FrameOut(BaseModel):
    index: int
    role: FrameRole
    height: int
    width: int
    dtype: str
    sha256: str


class AcquisitionOut(BaseModel):
    uid: str
    kind: AcquisitionKind
    patient: str | None = Field(description="Identifier, or pseudonym for researchers.")
    station_id: int | None
    calibration_id: int | None
    acquired_at: dt.datetime = Field(description="Shifted per patient for researchers.")
    operator: str | None
    notes: str | None
    frames: list[FrameOut]


class UploadOut(AcquisitionOut):
    warnings: list[str] = Field(
        default_factory=list,
        description="Stored, but: e.g. no calibration applies yet, so the frame size was not "
        "checked against a camera (which case, and why).")


class ResultOut(BaseModel):
    id: int
    stage: str
    plugin: str
    plugin_version: str
    plugin_package: str
    frame_index: int
    params: dict[str, Any]
    params_hash: str
    chain_key: str
    input_checksum: str
    output_checksum: str
    record_kind: str
    calibration_id: int | None
    reason: str
    package_version: str
    duration_s: float
    created_at: dt.datetime


class RunOut(BaseModel):
    id: int
    status: str
    chain: list[dict[str, Any]]
    started_at: dt.datetime
    finished_at: dt.datetime | None
    error: str
    computed: int
    reused: int


class JobIn(BaseModel):
    uids: list[str] = Field(min_length=1, max_length=10_000)
    chain: dict[str, str] = Field(default_factory=dict, description="stage kind -> plugin")
    params: dict[str, JsonObject] = Field(default_factory=dict)
    calibration_station: str | None = None
    calibration_version: int | None = Field(None, ge=1, le=2**31)
    until: str | list[Annotated[str, Field(max_length=64)]] = Field(
        default_factory=lambda: ["mesh", "analysis"],
        description="Last stage kind, or several (each its own chain; shared stages run once). "
        "Default: the mesh and the back-shape analysis, as `rasterserver process`.",
    )


class JobOutcomeOut(BaseModel):
    uid: str
    status: str
    computed: int
    reused: int
    reason: str
    error: str


class JobOut(BaseModel):
    id: str
    status: str = Field(description="queued, running, paused, cancelled, done or failed (also "
                        "when the server running it stopped: see error)")
    done: int = Field(description="Acquisitions processed to the end.")
    failed: int = Field(0, description="Acquisitions that failed (each in outcomes).")
    left: int = Field(0, description="Acquisitions not processed yet.")
    total: int
    rate_per_s: float | None = Field(None, description="Acquisitions finished per second.")
    eta_s: float | None = Field(None, description="Seconds left at that rate, while running.")
    created_at: dt.datetime
    started_at: dt.datetime | None = None
    progress_at: dt.datetime | None = Field(None, description="When an acquisition last "
                                            "finished.")
    finished_at: dt.datetime | None
    error: str
    outcomes: list[JobOutcomeOut]


class AuditOut(BaseModel):
    id: int
    request_id: str
    recorded_at: str
    actor: str
    actor_kind: str
    role: str
    action: str
    method: str
    route: str
    status: int
    patients: list[str] = Field(description="Identifiers of the patients whose data the "
                                "request touched.")
    acquisition: str | None
    client: str


class FieldErrorOut(BaseModel):
    """One refused field of a request (FastAPI's validation)."""

    loc: list[str | int] = Field(description="Where: body, query, path or header, then names.")
    msg: str
    type: str


class ErrorOut(BaseModel):
    """The body of every error response (see :mod:`rasterserver.api.errors`)."""

    detail: str | list[FieldErrorOut] = Field(
        description="What was wrong: a sentence, or the refused fields of a validation error.")
    error: str = Field(description="Kind of error, e.g. NotFoundError, ValidationError.")
    status: int = Field(description="The HTTP status code, repeated.")
