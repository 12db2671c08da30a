"""Who may call what: one table, keyed by route name, read by :func:`~.auth.authorize`.

The roles:

``admin``
    Accounts, stations, rasters, calibrations, the audit trail and metrics; no patient data.
``clinician``
    Patients, visits, acquisitions, frames, processing, results, analyses and exports.
``station``
    Uploads acquisitions, nothing else (a service account on an acquisition station).
``researcher``
    Reads patients, acquisitions, frames, results, analyses and exports, pseudonymised
    (see :mod:`rasterserver.services.pseudonyms`); writes nothing.

A route missing from :data:`RULES` is refused to everyone (and a test fails), so a new
route cannot go out unprotected by accident.
"""

from __future__ import annotations

ADMIN, CLINICIAN, STATION, RESEARCHER = "admin", "clinician", "station", "researcher"
EVERYONE = frozenset({ADMIN, CLINICIAN, STATION, RESEARCHER})
READERS = frozenset({CLINICIAN, RESEARCHER})

#: Routes that need no token at all.
PUBLIC = frozenset({"health", "openapi", "swagger_ui_html", "swagger_ui_redirect", "redoc_html"})

RULES: dict[str, frozenset[str]] = {
    # catalogue set-up
    "list_plugins": frozenset({ADMIN, CLINICIAN, RESEARCHER}),
    "metrics": frozenset({ADMIN}),
    "list_accounts": frozenset({ADMIN}),
    "add_account": frozenset({ADMIN}),
    "list_stations": frozenset({ADMIN, CLINICIAN, RESEARCHER}),
    "add_station": frozenset({ADMIN}),
    "get_station": frozenset({ADMIN, CLINICIAN, RESEARCHER}),
    "add_raster": frozenset({ADMIN}),
    "get_raster": frozenset({ADMIN, CLINICIAN, RESEARCHER}),
    "list_calibrations": frozenset({ADMIN, CLINICIAN, RESEARCHER}),
    "add_calibration": frozenset({ADMIN}),
    "get_calibration": frozenset({ADMIN, CLINICIAN, RESEARCHER}),
    # patient data
    "list_patients": READERS,
    "add_patient": frozenset({CLINICIAN}),
    "get_patient": READERS,
    "list_visits": READERS,
    "list_acquisitions": READERS,
    "upload_acquisition": frozenset({CLINICIAN, STATION}),
    "get_acquisition": READERS,
    "get_frame": READERS,
    "get_frame_preview": READERS,
    "list_results": READERS,
    "get_result": READERS,
    "list_runs": READERS,
    "export_result": READERS,
    "get_analysis": READERS,
    "get_analysis_report": READERS,
    "get_analysis_report_pdf": READERS,
    "get_comparison": READERS,
    "get_comparison_distance": READERS,
    "get_patient_trends": READERS,
    "start_job": frozenset({CLINICIAN}),
    "list_jobs": frozenset({CLINICIAN}),
    "get_job": frozenset({CLINICIAN}),
    "pause_job": frozenset({CLINICIAN}),
    "resume_job": frozenset({CLINICIAN}),
    "cancel_job": frozenset({CLINICIAN}),
    # oversight
    "get_audit": frozenset({ADMIN}),
}


def allowed(route_name: str, role: str) -> bool:
    """Return whether ``role`` may call the route called ``route_name``."""
    return role in RULES.get(route_name, frozenset())
