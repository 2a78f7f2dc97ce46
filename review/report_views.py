"""The report page: the figures of ``keystone report`` with two plots, for curators and exporters."""

from __future__ import annotations

import hashlib
from typing import Any

from flask import Blueprint, Response, render_template, request

from core.auth import add_nav_link, role_required

from .report import build_report, plot_confusion, plot_distribution
from .report_charts import confusion_shades, grade_bars

bp = Blueprint("reports", __name__, url_prefix="/reports", template_folder="templates")
bp.record_once(lambda state: add_nav_link(state.app, "Report", "reports.index", "curator", "exporter", order=60))

PLOTS = {"grades": plot_distribution, "agreement": plot_confusion}


@bp.route("/")
@role_required("curator", "exporter")
def index() -> Any:
    report = build_report()
    return render_template(
        "report/index.html",
        report=report,
        bars=grade_bars(report),
        shades=confusion_shades(report["automatic_vs_curator"]["confusion"]),
    )


@bp.route("/<name>.png")
@role_required("curator", "exporter")
def plot(name: str) -> Response:
    if name not in PLOTS:
        return Response(f"no plot named {name!r}; expected one of {', '.join(PLOTS)}", status=404, mimetype="text/plain")
    picture = PLOTS[name](build_report())
    etag = hashlib.sha256(picture).hexdigest()[:32]
    if etag in request.if_none_match:
        return Response(status=304)
    response = Response(picture, mimetype="image/png")
    response.set_etag(etag)
    response.headers["Cache-Control"] = "private, no-cache"
    return response
