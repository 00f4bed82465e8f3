"""A fault-injecting HTTP proxy for the store tests (issue 32), and a plain HTTP file server with or without
range requests.

:class:`FaultProxy` stands between prism-stream and an HTTP server (moto's S3 stand-in, or
:class:`FileServer`): it forwards every request and, at the request a test chooses, answers with a fault
instead: ``refuse`` (close the connection unanswered), ``stall`` (hold the connection, answer nothing, until
the proxy stops), ``cut`` (send the headers and half the body, then close; a HEAD's headers are cut), or
``status:CODE`` (an error status with an S3-style XML body). A fault is *sticky* from the chosen request on (a
store that went down stays down), or hits a number of requests of one operation (``times``).

Requests are named by the operation a store client makes (:func:`operation`), so a test says "the second
upload part" rather than a URL pattern.
"""

from __future__ import annotations

import http.client
import http.server
import os
import socket
import socketserver
import threading
import time
import urllib.parse
from pathlib import Path

HOP = {"connection", "keep-alive", "proxy-connection", "transfer-encoding", "upgrade", "te", "trailer"}


def operation(method: str, target: str, headers) -> str:
    """The S3 (or HTTP) operation a request is: list, head, read, range, create_multipart, upload_part,
    complete_multipart, abort_multipart, put, delete, bucket, other."""
    parsed = urllib.parse.urlsplit(target)
    query = urllib.parse.parse_qs(parsed.query, keep_blank_values=True)
    path = parsed.path.strip("/")
    if method == "HEAD":
        return "head" if "/" in path else "bucket"
    if method == "GET":
        if "list-type" in query or "/" not in path and path:
            return "list"
        return "range" if headers.get("Range") else "read"
    if method == "POST":
        if "uploads" in query:
            return "create_multipart"
        if "uploadId" in query:
            return "complete_multipart"
        if "delete" in query:
            return "delete"
    if method == "PUT":
        return "upload_part" if "partNumber" in query else "put"
    if method == "DELETE":
        return "abort_multipart" if "uploadId" in query else "delete"
    return "other"


class _Server(socketserver.ThreadingMixIn, http.server.HTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def handle_error(self, request, client_address):  # a client that hung up (the faults' own doing): quiet
        pass


class FaultProxy:
    """A proxy on 127.0.0.1 in front of ``upstream`` (``http://host:port``); :attr:`url` is its address."""

    def __init__(self, upstream: str):
        split = urllib.parse.urlsplit(upstream)
        self.upstream = (split.hostname, split.port)
        self.log: list[str] = []  # operations seen, in order
        self.faulted: list[str] = []  # operations answered with the fault
        self._lock = threading.Lock()
        self._fault = None  # (operation, nth, fault, once)
        self._seen: dict[str, int] = {}
        self._tripped = False
        self.tripped_at = None  # time.monotonic() of the first fault
        self._stop = threading.Event()
        proxy = self

        class Handler(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args):  # quiet
                pass

            def _body(self) -> bytes:
                if self.headers.get("Transfer-Encoding", "").lower() == "chunked":
                    out = bytearray()
                    while True:
                        size = int(self.rfile.readline().split(b";")[0].strip() or b"0", 16)
                        if size == 0:
                            while self.rfile.readline() not in (b"\r\n", b"\n", b""):
                                pass
                            return bytes(out)
                        out += self.rfile.read(size)
                        self.rfile.readline()
                length = int(self.headers.get("Content-Length") or 0)
                return self.rfile.read(length) if length else b""

            def _handle(self):
                body = self._body()
                op = operation(self.command, self.path, self.headers)
                fault = proxy._decide(op)
                if fault is not None:
                    return self._fail(fault, op)
                conn = http.client.HTTPConnection(*proxy.upstream, timeout=60)
                headers = {k: v for k, v in self.headers.items() if k.lower() not in HOP}
                if body or self.command in ("PUT", "POST"):
                    headers["Content-Length"] = str(len(body))
                conn.request(self.command, self.path, body=body, headers=headers)
                response = conn.getresponse()
                data = response.read()
                conn.close()
                self.send_response(response.status, response.reason)
                for k, v in response.getheaders():
                    if k.lower() not in HOP and k.lower() != "content-length":
                        self.send_header(k, v)
                self.send_header("Content-Length", str(len(data) if self.command != "HEAD" else
                                                       response.getheader("Content-Length") or 0))
                self.end_headers()
                if self.command != "HEAD":
                    self.wfile.write(data)

            def _fail(self, fault: str, op: str):
                if fault == "refuse":
                    self.close_connection = True
                    self.connection.shutdown(socket.SHUT_RDWR)
                    return
                if fault == "stall":
                    proxy._stop.wait()
                    self.close_connection = True
                    return
                if fault == "cut" and self.command == "HEAD":  # no body to cut: the headers are cut instead
                    self.wfile.write(b"HTTP/1.1 200 OK\r\nContent-Le")
                    self.wfile.flush()
                    self.close_connection = True
                    self.connection.shutdown(socket.SHUT_RDWR)
                    return
                if fault == "cut":
                    body = os.urandom(1 << 16)
                    self.send_response(200 if not self.headers.get("Range") else 206)
                    self.send_header("Content-Length", str(len(body)))
                    self.end_headers()
                    self.wfile.write(body[: len(body) // 2])
                    self.wfile.flush()
                    self.close_connection = True
                    self.connection.shutdown(socket.SHUT_RDWR)
                    return
                code = int(fault.split(":")[1])
                xml = (f"<?xml version='1.0' encoding='UTF-8'?><Error><Code>InjectedFault{code}</Code>"
                       f"<Message>injected by the test proxy at {op}</Message></Error>").encode()
                self.send_response(code)
                self.send_header("Content-Type", "application/xml")
                self.send_header("Content-Length", str(len(xml) if self.command != "HEAD" else 0))
                self.end_headers()
                if self.command != "HEAD":
                    self.wfile.write(xml)

            do_GET = do_PUT = do_POST = do_HEAD = do_DELETE = _handle

        self._server = _Server(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self._server.server_address[1]}"
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)
        self._thread.start()

    def arm(self, op: str, fault: str, nth: int = 1, times: int | None = None) -> None:
        """Answer the ``nth`` request of operation ``op`` with ``fault``, and every request after it (the store
        went down), or with ``times`` the next ``times`` requests of ``op`` only (a store failing one kind of
        request a while)."""
        with self._lock:
            self._fault = (op, nth, fault, times)
            self._seen = {}
            self._tripped = False
            self.tripped_at = None
            self.faulted = []

    def disarm(self) -> None:
        with self._lock:
            self._fault = None
            self._tripped = False

    def _decide(self, op: str):
        with self._lock:
            self.log.append(op)
            self._seen[op] = self._seen.get(op, 0) + 1
            if self._fault is None:
                return None
            target, nth, fault, times = self._fault
            if op == target and self._seen[op] >= nth and (times is None or len(self.faulted) < times):
                if not self._tripped:
                    self._tripped = True
                    self.tripped_at = time.monotonic()
                self.faulted.append(op)
                return fault
            if self._tripped and times is None:
                self.faulted.append(op)
                return fault
            return None

    def close(self) -> None:
        self._stop.set()
        self._server.shutdown()
        self._server.server_close()


class FileServer:
    """A plain HTTP server of ``folder`` on 127.0.0.1, with or without range requests (``ranges``)."""

    def __init__(self, folder: Path, ranges: bool = True, refuse_ranges: bool = False):
        """``refuse_ranges``: say ``Accept-Ranges: none`` (and answer none), as some servers do."""
        root = Path(folder)

        class Handler(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args):
                pass

            def _send(self, head: bool):
                path = root / urllib.parse.unquote(urllib.parse.urlsplit(self.path).path).lstrip("/")
                if not path.is_file():
                    self.send_error(404)
                    return
                data = path.read_bytes()
                start, end = 0, len(data)
                status = 200
                spec = self.headers.get("Range") if ranges and not refuse_ranges else None
                if spec and spec.startswith("bytes="):
                    a, _, b = spec[6:].partition("-")
                    start = int(a) if a else max(0, len(data) - int(b))
                    end = min(len(data), int(b) + 1) if a and b else len(data)
                    status = 206
                self.send_response(status)
                if status == 206:
                    self.send_header("Content-Range", f"bytes {start}-{end - 1}/{len(data)}")
                if ranges or refuse_ranges:
                    self.send_header("Accept-Ranges", "none" if refuse_ranges else "bytes")
                self.send_header("Content-Length", str(end - start))
                self.end_headers()
                if not head:
                    self.wfile.write(data[start:end])

            def do_GET(self):
                self._send(False)

            def do_HEAD(self):
                self._send(True)

        self._server = _Server(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self._server.server_address[1]}"
        threading.Thread(target=self._server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
