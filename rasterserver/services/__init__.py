"""Services shared by the CLI and the HTTP API, free of any web framework.

- :mod:`~rasterserver.services.auth`: accounts and API tokens.
- :mod:`~rasterserver.services.token_cache`: the server's cache of token owners (PostgreSQL).
- :mod:`~rasterserver.services.audit`: audit records and their group-committed insertion
  (:mod:`~rasterserver.services.audit_writer`), the patient index of the trail
  (:mod:`~rasterserver.services.audit_index`) and reading it back, also as FHIR
  (:mod:`~rasterserver.services.audit_trail`).
- :mod:`~rasterserver.services.pseudonyms`: the researchers' pseudonyms and date shifts.
- :mod:`~rasterserver.services.patients`: filtered patient and visit listings.
- :mod:`~rasterserver.services.jobs`: processing jobs run by threads of a server process.

They take the catalogue (:class:`~rasterserver.catalog.catalog.Catalog`) for the database,
or the :class:`~rasterserver.archive.Archive` where they need its settings or stores. Nothing
here imports FastAPI or Starlette (``tests/services/test_services_imports.py``); the HTTP
side of them (the ``authorize`` dependency, the audit middleware) is in
:mod:`rasterserver.api`.
"""
