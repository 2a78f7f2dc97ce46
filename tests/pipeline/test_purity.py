"""pipeline/ stays pure: importing every module pulls in neither Flask, SQLAlchemy nor torch."""

from __future__ import annotations

import json
import pkgutil
import subprocess
import sys

import pipeline


def test_pipeline_imports_no_web_database_or_torch():
    modules = [f"pipeline.{m.name}" for m in pkgutil.iter_modules(pipeline.__path__)]
    code = (
        "import importlib, json, sys\n"
        f"for name in {modules!r}: importlib.import_module(name)\n"
        "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in ('flask', 'sqlalchemy', 'torch', 'app'))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout) == []
    assert len(modules) >= 6
