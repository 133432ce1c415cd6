"""What the local web pages (the labeller, the live view) share: answering a request.

Both serve 127.0.0.1 from the standard library's ``http.server``; every answer carries its
length and ``Cache-Control: no-store`` (the page always shows the latest state).
"""

from __future__ import annotations

import json
from typing import Any

__all__ = ["send", "send_json"]


def send(handler, code: int, content_type: str, body: bytes) -> None:
    """Answer the request ``handler`` (a ``BaseHTTPRequestHandler``) is serving."""
    handler.send_response(code)
    handler.send_header("Content-Type", content_type)
    handler.send_header("Content-Length", str(len(body)))
    handler.send_header("Cache-Control", "no-store")
    handler.end_headers()
    handler.wfile.write(body)


def send_json(handler, code: int, obj: Any) -> None:
    """Answer with ``obj`` as JSON."""
    send(handler, code, "application/json", json.dumps(obj).encode())
