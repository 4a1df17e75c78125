"""The service's logs: one stderr handler on the `cortexloc` logger, JSON lines or text, each record
with the request id of the request it belongs to (docs/design/service.md §8)."""

from __future__ import annotations

import json
import logging
from datetime import UTC, datetime
from typing import Any

from service.request_ids import request_id_var
from service.settings import Settings

__all__ = ["JsonFormatter", "configure_logging"]


class _RequestIdFilter(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        record.request_id = request_id_var.get() or "-"
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per line: ts, level, logger, message, request_id, exc."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "ts": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname, "logger": record.name, "message": record.getMessage()}
        rid = getattr(record, "request_id", "-")
        if rid != "-":
            out["request_id"] = rid
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


def configure_logging(settings: Settings) -> None:
    """One stderr handler on the `cortexloc` logger with the configured level and format (idempotent)."""
    logger = logging.getLogger("cortexloc")
    for h in list(logger.handlers):
        if getattr(h, "_cortexloc", False):
            logger.removeHandler(h)
    handler = logging.StreamHandler()
    handler._cortexloc = True  # type: ignore[attr-defined]
    handler.addFilter(_RequestIdFilter())
    if settings.log_format == "json":
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(
            logging.Formatter("%(asctime)s %(levelname)s %(name)s [%(request_id)s] %(message)s"))
    logger.addHandler(handler)
    logger.setLevel(settings.log_level)
