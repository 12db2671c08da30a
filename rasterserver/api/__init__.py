"""The HTTP API: FastAPI routers over the same services the CLI uses.

:func:`rasterserver.api.app.create_app` builds the application; ``rasterserver serve`` runs
it on uvicorn. Authentication, roles, the audit trail and pseudonyms live in their own
modules here so that each rule is written once.
"""
