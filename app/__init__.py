"""Keystone's Flask shell: the app factory binds extensions and blueprints late."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from flask import Flask
from sqlalchemy.engine import Engine


def create_app(test_config: dict[str, Any] | None = None, instance_path: str | os.PathLike[str] | None = None) -> Flask:
    instance_path = instance_path or os.environ.get("KEYSTONE_INSTANCE_PATH")
    app = Flask(
        __name__,
        instance_path=str(Path(instance_path).resolve()) if instance_path else None,
        instance_relative_config=True,
    )
    Path(app.instance_path).mkdir(parents=True, exist_ok=True)

    from core.config import config_from_environment

    app.config.from_mapping(config_from_environment(app.instance_path))
    if test_config is not None:
        app.config.from_mapping(test_config)
    if app.config["SQLALCHEMY_DATABASE_URI"].startswith("sqlite"):
        app.config.setdefault("SQLALCHEMY_ENGINE_OPTIONS", {"connect_args": {"timeout": 30}})

    from core import limits
    from core.db import db
    from core.extensions import csrf, login_manager

    limits.init_app(app)  # first: blueprints bind its id converter, CSRF reads bodies it limits
    db.init_app(app)
    csrf.init_app(app)
    login_manager.init_app(app)

    from core.console import register_schema

    register_schema(app, _ensure_schema)

    from catalogue import views as catalog
    from core import auth, security

    app.register_blueprint(auth.bp)
    app.register_blueprint(catalog.bp)

    from annotation import bp as crowd_bp

    app.register_blueprint(crowd_bp)

    from catalogue import viewer
    from exports.views import bp as exports_bp
    from review.report_views import bp as reports_bp
    from review.views import bp as review_bp

    app.register_blueprint(review_bp)
    app.register_blueprint(reports_bp)
    app.register_blueprint(exports_bp)
    app.register_blueprint(viewer.bp)
    security.init_app(app)

    # keystone run clears what killed exports left in the releases folder; the driver below the
    # exports feature learns how from here, not by importing it.
    from exports.staging import remove_stale_partials
    from runs.leftovers import register_staging_cleaner

    register_staging_cleaner(app, remove_stale_partials)

    # Browsers ask for /favicon.ico on pages that name no icon (JSON, images opened alone): the
    # app's icon, not a 404 in every console.
    @app.get("/favicon.ico")
    def favicon() -> Any:
        return app.send_static_file("favicon.svg")

    return app


def _ensure_schema(engine: Engine) -> bool:
    """:func:`app.schema.ensure_schema`, imported when a command first needs it (Alembic is slow to import)."""
    from app.schema import ensure_schema

    return ensure_schema(engine)
