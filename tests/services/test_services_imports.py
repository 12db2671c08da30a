"""The services are free of the web framework, and the CLI's account, token and audit
commands run without loading it (issue 17).

Fresh interpreters, so that what another test imported does not count: one imports every
module of :mod:`rasterserver.services`, the other runs the token commands in-process with
:func:`rasterserver.cli.main` and reports ``sys.modules`` afterwards.
"""

from __future__ import annotations

import json
import os
import pkgutil
import subprocess
import sys
from pathlib import Path

import rasterserver.services

#: The web framework and its server: the HTTP API's business, not the services'.
WEB = ("fastapi", "starlette", "uvicorn")

#: Runs CLI commands in-process, one after another (each must succeed), and writes the
#: loaded modules as JSON to the file named by the first argument. Commands are separated
#: by a lone "--next".
HOOK = """
import json, sys
from rasterserver.cli import main
report, args = sys.argv[1], sys.argv[2:]
commands, current = [], []
for arg in args:
    if arg == "--next":
        commands.append(current)
        current = []
    else:
        current.append(arg)
commands.append(current)
codes = [main(command) for command in commands]
with open(report, "w") as f:
    json.dump({"exits": codes, "modules": sorted(sys.modules)}, f)
"""


def web_modules(modules: list[str]) -> list[str]:
    """The modules of ``modules`` that belong to a :data:`WEB` package."""
    return sorted(m for m in modules if any(m == w or m.startswith(w + ".") for w in WEB))


def clean_env() -> dict[str, str]:
    """The test's environment without RASTERSERVER_* settings and import-time logging."""
    drop = ("RASTERSERVER_", "PYTHONPROFILEIMPORTTIME")
    return {k: v for k, v in os.environ.items() if not k.startswith(drop)}


def loaded_after(code: str, *args: str, cwd: Path) -> dict:
    """Run ``code`` (which writes a JSON report to ``sys.argv[1]``) in a fresh interpreter."""
    report = cwd / "report.json"
    done = subprocess.run([sys.executable, "-c", code, str(report), *args],
                          capture_output=True, text=True, timeout=300, check=False,
                          env=clean_env(), cwd=cwd)
    assert report.exists(), f"no report\n{done.stdout}\n{done.stderr}"
    return json.loads(report.read_text())


def test_services_import_no_web_framework(tmp_path: Path) -> None:
    names = sorted(f"rasterserver.services.{m.name}"
                   for m in pkgutil.iter_modules(rasterserver.services.__path__))
    assert "rasterserver.services.auth" in names and "rasterserver.services.audit" in names
    code = ("import importlib, json, sys\n"
            "for name in sys.argv[2:]:\n"
            "    importlib.import_module(name)\n"
            "json.dump({'modules': sorted(sys.modules)}, open(sys.argv[1], 'w'))\n")
    modules = loaded_after(code, *names, cwd=tmp_path)["modules"]
    assert not web_modules(modules), web_modules(modules)


def test_token_commands_run_without_web_framework(tmp_path: Path) -> None:
    root = tmp_path / "archive"
    opt = ["--archive", str(root)]
    commands = [
        [*opt, "db", "upgrade"],
        [*opt, "user", "add", "dr-who", "--role", "clinician"],
        [*opt, "user", "list"],
        [*opt, "token", "create", "dr-who", "--label", "test"],
        [*opt, "token", "list"],
        [*opt, "token", "revoke", "1"],
        [*opt, "user", "disable", "dr-who"],
        [*opt, "audit", "export", "-o", str(tmp_path / "audit.json")],
    ]
    args = [a for i, c in enumerate(commands) for a in ([*c] if i == 0 else ["--next", *c])]
    result = loaded_after(HOOK, *args, cwd=tmp_path)
    assert result["exits"] == [0] * len(commands)
    assert not web_modules(result["modules"]), web_modules(result["modules"])
    bundle = json.loads((tmp_path / "audit.json").read_text())
    # user add, token create, token revoke, user disable
    assert bundle["total"] == 4
