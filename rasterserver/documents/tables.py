"""The documents' JSON Schema as documentation: the field tables of ``docs/formats.md`` and
the schema files of ``docs/schemas/``, both generated from the models (tests check drift)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from rasterserver.documents.calibration_document import CalibrationDocument
from rasterserver.documents.raster_document import RasterDocument


def _type_text(schema: dict[str, Any], defs: dict[str, Any]) -> str:
    if "$ref" in schema:
        return defs[schema["$ref"].rsplit("/", 1)[-1]].get("title", "object")
    if "const" in schema:
        return f'`"{schema["const"]}"`'
    if "enum" in schema:
        return " or ".join(f'`"{v}"`' for v in schema["enum"])
    if "anyOf" in schema or "oneOf" in schema:
        options = schema.get("anyOf") or schema["oneOf"]
        shown = [_type_text(o, defs) for o in options if o.get("type") != "null"]
        nullable = any(o.get("type") == "null" for o in options)
        return " or ".join(shown) + (" (or null)" if nullable else "")
    kind = schema.get("type")
    if kind == "array":
        items = schema.get("items", {})
        n = schema.get("minItems")
        fixed = n is not None and n == schema.get("maxItems")
        inner = _type_text(items, defs)
        if items.get("type") == "array" and fixed:
            m = items.get("minItems")
            return f"{n}×{m} numbers" if items.get("items", {}).get("type") == "number" else inner
        if fixed and items.get("type") == "number":
            return f"{n} numbers"
        if items.get("type") == "number":
            return f"{n}–{schema.get('maxItems')} numbers"
        return f"array of {inner}"
    if "minimum" in schema and "maximum" in schema:
        return f"{kind}, {schema['minimum']} to {schema['maximum']}"
    bounds = []
    for key, sign in (("minimum", "≥"), ("exclusiveMinimum", ">"), ("maximum", "≤")):
        if key in schema:
            bounds.append(f"{sign} {schema[key]}")
    return " ".join([str(kind), *bounds]) if kind else "any"


def _table(schema: dict[str, Any], defs: dict[str, Any]) -> list[str]:
    rows = ["| field | type | required | meaning |", "|---|---|---|---|"]
    required = set(schema.get("required", ()))
    for name, prop in schema["properties"].items():
        if name in required:
            need = "yes"
        elif "default" in prop and prop["default"] is not None:
            need = f"no (`{json.dumps(prop['default'])}`)"
        else:
            need = "no"
        if len(need) > 30:  # long defaults (a 3×3 identity) in words
            need = "no (identity)" if name == "R" else "no (zeros)"
        text = prop.get("description", "").replace("|", "\\|")
        rows.append(f"| `{name}` | {_type_text(prop, defs)} | {need} | {text} |")
    return rows


def format_tables() -> dict[str, str]:
    """Markdown field tables of both documents, generated from the models' JSON Schema.

    ``docs/formats.md`` holds them between ``<!-- generated: KEY -->`` and
    ``<!-- end generated -->`` markers; a test fails when they differ from the models.

    Returns
    -------
    dict
        ``{"calibration": ..., "device": ..., "raster": ..., "raster-code": ...,
        "raster-line": ...}``, each a table (no trailing newline).
    """
    calibration = CalibrationDocument.model_json_schema()
    raster = RasterDocument.model_json_schema()
    cdefs, rdefs = calibration["$defs"], raster["$defs"]
    camera, projector = cdefs["CameraDocument"], cdefs["ProjectorDocument"]
    # one device table: the fields both share, with the camera's and projector's sizes
    shared = dict(camera["properties"])
    sizes = {
        side: {
            "type": "camera: integer ≥ 1; projector: number > 0",
            "description": f"camera: {shared.pop(side)['description']}; projector: "
            f"{projector['properties'][side]['description']}",
        }
        for side in ("width", "height")
    }
    model = {"model": shared.pop("model")}
    device = {"properties": model | sizes | shared, "required": camera["required"]}
    return {
        "calibration": "\n".join(_table(calibration, cdefs)),
        "device": "\n".join(_table(device, cdefs)),
        "raster": "\n".join(_table(raster, rdefs)),
        "raster-code": "\n".join(_table(rdefs["RasterCode"], rdefs)),
        "raster-line": "\n".join(_table(rdefs["RasterLine"], rdefs)),
    }


_GENERATED = re.compile(
    r"(<!-- generated from rasterserver\.documents\.format_tables\(\): ([a-z-]+) -->\n)"
    r".*?(<!-- end generated -->)",
    re.S,
)


def fill_format_tables(markdown: str) -> str:
    """``markdown`` with every generated block replaced by the current :func:`format_tables`.

    A block is ``<!-- generated from rasterserver.documents.format_tables(): KEY -->``, the
    table, ``<!-- end generated -->``; text outside the blocks is kept as it is.
    """
    tables = format_tables()
    return _GENERATED.sub(lambda m: f"{m[1]}{tables[m[2]]}\n{m[3]}", markdown)


#: The schema files of ``docs/schemas/``, by the document they describe.
SCHEMA_FILES: dict[str, type[BaseModel]] = {
    "calibration.schema.json": CalibrationDocument,
    "raster.schema.json": RasterDocument,
}


def json_schemas() -> dict[str, str]:
    """The JSON Schema (draft 2020-12) of each document, as the text of its file.

    Returns
    -------
    dict
        File name (``calibration.schema.json``, ``raster.schema.json``) to the schema's JSON,
        indented, ending with a newline; what ``docs/schemas/`` holds (a test checks drift).
    """
    texts = {}
    for name, model in SCHEMA_FILES.items():
        schema: dict[str, Any] = {"$schema": "https://json-schema.org/draft/2020-12/schema"}
        schema |= model.model_json_schema()
        texts[name] = json.dumps(schema, indent=2, ensure_ascii=False) + "\n"
    return texts


def write_json_schemas(folder: Path) -> list[Path]:
    """Write :func:`json_schemas` into ``folder`` (created if needed); return the files."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in json_schemas().items():
        path = folder / name
        path.write_text(text, encoding="utf-8")
        written.append(path)
    return written
