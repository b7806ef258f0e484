"""An MJPEG network camera for tests: ``multipart/x-mixed-replace`` JPEG frames over HTTP on
127.0.0.1, as IP cameras serve them. ``stop()`` ends every stream and closes the port (the
camera is unplugged), ``start()`` serves again on the same port."""

from __future__ import annotations

import http.server
import socketserver
import threading
import time
from collections.abc import Callable

import cv2
import numpy as np

BOUNDARY = b"cellcalframe"


class MJPEGCamera:
    """Serves ``frame()`` (uint8 (H, W) or (H, W, 3)) every ``period`` seconds at ``url``."""

    def __init__(self, frame: Callable[[], np.ndarray], *, period: float = 0.02) -> None:
        self.frame, self.period = frame, period
        self._serving = threading.Event()
        self._server: socketserver.ThreadingTCPServer | None = None
        self.port = 0
        self.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/video.mjpg"

    def start(self) -> None:
        """Serve (again, on the same port)."""
        camera = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                self.send_response(200)
                self.send_header("Content-Type",
                                 f"multipart/x-mixed-replace; boundary={BOUNDARY.decode()}")
                self.end_headers()
                while camera._serving.is_set():
                    ok, jpeg = cv2.imencode(".jpg", camera.frame())
                    assert ok
                    part = (b"--" + BOUNDARY + b"\r\nContent-Type: image/jpeg\r\n"
                            b"Content-Length: %d\r\n\r\n" % len(jpeg) + jpeg.tobytes() + b"\r\n")
                    try:
                        self.wfile.write(part)
                    except OSError:
                        return
                    time.sleep(camera.period)

            def log_message(self, *args: object) -> None:
                pass

        server = socketserver.ThreadingTCPServer(("127.0.0.1", self.port), Handler,
                                                 bind_and_activate=False)
        server.allow_reuse_address = server.daemon_threads = True
        server.server_bind()
        server.server_activate()
        self.port = server.server_address[1]
        self._serving.set()
        self._server = server
        threading.Thread(target=server.serve_forever, daemon=True).start()

    def stop(self) -> None:
        """End every stream and stop listening."""
        self._serving.clear()
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None
