"""The product never imports the benchmarks: ``keystone bench NAME`` loads one only when it runs
(or when ``keystone bench --help`` lists them)."""

from __future__ import annotations

import json
import pkgutil
import subprocess
import sys

import annotation
import app
import exports
import pipeline
import review


def test_no_product_module_imports_the_benchmarks():
    modules = [
        f"{package.__name__}.{m.name}"
        for package in (app, annotation, review, pipeline, exports)
        for m in pkgutil.iter_modules(package.__path__)
        if m.name != "__main__"
    ]
    code = (
        "import importlib, json, sys\n"
        f"for name in {modules!r}: importlib.import_module(name)\n"
        "from app import create_app\n"
        "create_app({'SQLALCHEMY_DATABASE_URI': 'sqlite://'})\n"
        "from app.cli import cli\n"
        "cli.main(['--help'], standalone_mode=False)\n"
        "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] == 'benchmarks')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []
    assert len(modules) >= 40


def test_bench_help_lists_every_benchmark_and_loads_one_on_use(runner):
    from app.bench import LAZY_BENCHMARKS

    listing = runner.invoke(args=["bench", "--help"])
    assert listing.exit_code == 0
    for name in LAZY_BENCHMARKS:
        assert f"  {name} " in listing.output
    result = runner.invoke(args=["bench", "rectify", "--help"])
    assert result.exit_code == 0 and "keystone vs hartley" in result.output
