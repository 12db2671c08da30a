"""The HTTP API: FastAPI routers over the same services the CLI uses.

:func:`rasterserver.api.app.create_app` builds the application; ``rasterserver serve`` runs
it on uvicorn. The services themselves (accounts and tokens, the audit trail, pseudonyms,
jobs) are :mod:`rasterserver.services`, free of FastAPI; here is only their HTTP side: the
``authorize`` dependency and the gate (:mod:`~rasterserver.api.auth`,
:mod:`~rasterserver.api.gate`), the role table (:mod:`~rasterserver.api.roles`), the audit
middleware (:mod:`~rasterserver.api.audit`), and routers that translate requests into
service calls and records into schemas (:mod:`~rasterserver.api.views`).
"""
