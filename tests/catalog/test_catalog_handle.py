"""The catalogue handle (:class:`rasterserver.catalog.catalog.Catalog`) and the schema check
without Alembic (:mod:`rasterserver.catalog.schema`)."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import select, text

from rasterserver.catalog import migrate, schema
from rasterserver.catalog.catalog import Catalog
from rasterserver.catalog.database import make_engine
from rasterserver.catalog.models import Patient
from rasterserver.config import Settings


def test_the_head_read_from_the_files_is_alembics() -> None:
    engine = make_engine("sqlite://")
    assert schema.head_revision_id() == migrate.head_revision(engine)


def test_current_revision_agrees_with_alembic(database_url: str) -> None:
    engine = make_engine(database_url)
    assert schema.current_revision(engine) is None
    migrate.upgrade(engine, "0005")
    assert schema.current_revision(engine) == migrate.current_revision(engine) == "0005"
    with pytest.raises(schema.SchemaError, match=r"is at revision 0005.*rasterserver db upgrade"):
        schema.require_current(engine)
    migrate.upgrade(engine)
    assert schema.current_revision(engine) == migrate.current_revision(engine)
    schema.require_current(engine)
    engine.dispose()


def test_a_catalog_refuses_an_unmigrated_database(database_url: str) -> None:
    with pytest.raises(schema.SchemaError, match="is empty"):
        Catalog(database_url)
    with Catalog(database_url, check_schema=False) as catalog:
        assert catalog.dialect in ("sqlite", "postgresql")


def test_create_migrates_then_sessions_commit_and_roll_back(database_url: str) -> None:
    with Catalog.create(database_url) as catalog:
        with catalog.session() as s:
            s.add(Patient(identifier="P1"))
        with pytest.raises(RuntimeError), catalog.session() as s:
            s.add(Patient(identifier="P2"))
            s.flush()
            raise RuntimeError("rolled back")
        with catalog.reading() as conn:
            names = list(conn.scalars(select(Patient.identifier)))
        assert names == ["P1"]
        with catalog.write_lock(), catalog.engine.begin() as conn:
            assert conn.execute(text("SELECT 1")).scalar() == 1


def test_an_archive_borrows_a_catalog_and_leaves_it_open(tmp_path: Path,
                                                         database_url: str) -> None:
    from rasterserver.archive import Archive

    settings = Settings(archive=tmp_path / "archive", database_url=database_url)
    with Catalog.create(database_url) as catalog:
        with Archive(settings, catalog=catalog) as archive:
            assert archive.catalog is catalog and archive.engine is catalog.engine
            archive.add_patient("P1")
        with catalog.session() as s:  # still open
            assert s.scalar(select(Patient.identifier)) == "P1"


def test_the_light_column_views_match_the_models() -> None:
    """rasterserver.catalog.columns names real columns, with the types that decode them."""
    from rasterserver.catalog import columns
    from rasterserver.catalog.models import Base

    for view in (columns.patient, columns.acquisition, columns.frame):
        model = Base.metadata.tables[view.name]
        for col in view.columns:
            assert col.name in model.columns, f"{view.name}.{col.name}"
            assert type(col.type)._type_affinity is type(  # type: ignore[attr-defined]
                model.columns[col.name].type)._type_affinity, f"{view.name}.{col.name}"


def test_listing_starts_without_the_orm() -> None:
    import subprocess
    import sys

    code = ("import sys, rasterserver.catalog.listing, rasterserver.catalog.catalog; "
            "print(sorted(m for m in sys.modules if m in ('sqlalchemy.orm', "
            "'rasterserver.catalog.models', 'alembic', 'numpy', 'h5py')))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True)
    assert done.stdout.strip() == "[]"
