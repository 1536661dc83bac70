"""A meshcat-protocol server bound to one address (127.0.0.1 by default), running in a background thread.

meshcat's own server listens on every interface (tornado's `listen(port)` with no address): anyone on the
network could watch, or drive the page. This one binds the address it is given, serves our page, meshcat's
viewer JavaScript and a WebSocket that carries meshcat's msgpack commands, and keeps the scene so that a page
opened (or reloaded) later gets everything sent so far.
"""

from __future__ import annotations

import asyncio
import ipaddress
import socket
import threading
import warnings
from collections.abc import Callable
from typing import Any

from ..exceptions import InvalidArgumentError
from ..validation import check_text, port_number
from ._deps import ViewerWarning, meshcat_viewer_js, require
from .page import live_page
from .scene import pack

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORTS = range(7000, 7100)  # meshcat's habit: 7000, or the next free one
_ORDER = {"object": 0, "property": 1, "transform": 2, "animation": 3, "custom": 4}


class ExposedServerWarning(ViewerWarning):
    """The viewer listens on an address other machines can reach."""


class MeshcatServer:
    """Serve meshcat's viewer on host:port and stream commands to every open page.

    Args:
        host: address to bind; 127.0.0.1 (the default) keeps the viewer on this machine. Anything that is not
            a loopback address warns (ExposedServerWarning).
        port: TCP port; None tries 7000 to 7099 and then lets the system choose; 0 lets the system choose.
        title: the page title.

    Attributes:
        url: the page's address.
        address: (host, port) actually bound.
    """

    def __init__(self, host: str = DEFAULT_HOST, port: int | None = None, *, title: str = "multibody-sim"):
        if not isinstance(host, str):
            raise InvalidArgumentError(f"host must be an address such as {DEFAULT_HOST!r}, got {type(host).__name__}")
        port = port_number(port)
        check_text(title, "title", optional=False)
        tornado_web = require("tornado.web", "the meshcat viewer")
        tornado_websocket = require("tornado.websocket", "the meshcat viewer")
        tornado_netutil = require("tornado.netutil", "the meshcat viewer")
        self._viewer_js = meshcat_viewer_js().read_bytes()
        self._page = live_page(title).encode("utf-8")
        if not _is_loopback(host):
            warnings.warn(
                f"the viewer listens on {host!r}: other machines that reach this one can open it "
                f"(use {DEFAULT_HOST} to keep it local)",
                ExposedServerWarning,
                stacklevel=2,
            )
        self._sockets = _bind(tornado_netutil, host, port)
        self.address: tuple[str, int] = self._sockets[0].getsockname()[:2]
        shown = socket.gethostname() if host in ("0.0.0.0", "::", "") else host
        shown = f"[{shown}]" if ":" in shown else shown
        self.url = f"http://{shown}:{self.address[1]}/"

        self._lock = threading.Lock()
        self._scene: dict[tuple[str, ...], bytes] = {}
        self._clients: set[Any] = set()
        self._loaded = threading.Event()
        self._loop: Any = None
        self._started = threading.Event()
        server = self

        # A loopback server answers only requests addressed to a loopback name: a web page whose domain is made
        # to resolve to 127.0.0.1 (DNS rebinding) gets nothing. tornado's check_origin already refuses
        # WebSocket connections from pages of other origins.
        local_names = {"127.0.0.1", "localhost", "[::1]", "::1", host} if _is_loopback(host) else None

        def addressed_here(handler: Any) -> bool:
            if local_names is None:
                return True
            return str(handler.request.host_name).lower() in local_names

        class Page(tornado_web.RequestHandler):  # type: ignore[misc, name-defined]
            def prepare(self) -> None:
                if not addressed_here(self):
                    raise tornado_web.HTTPError(403)

            def get(self) -> None:
                self.set_header("Content-Type", "text/html; charset=utf-8")
                self.set_header("Cache-Control", "no-store")
                self.write(server._page)

        class ViewerScript(Page):  # type: ignore[misc, valid-type]
            def get(self) -> None:
                self.set_header("Content-Type", "application/javascript")
                self.write(server._viewer_js)

        class Commands(tornado_websocket.WebSocketHandler):  # type: ignore[misc, name-defined]
            # tornado's default check_origin refuses pages from other origins: another site open in the same
            # browser cannot connect to this socket.
            def prepare(self) -> None:
                if not addressed_here(self):
                    raise tornado_web.HTTPError(403)

            def open(self) -> None:
                with server._lock:
                    backlog = [server._scene[k] for k in sorted(server._scene, key=lambda k: _ORDER[k[0]])]
                    server._clients.add(self)
                for message in backlog:
                    if not server._write(self, message):
                        break  # the page left while it was being sent the scene

            def on_message(self, message: Any) -> None:
                # Our page says when it has applied the scene; meshcat's pages send only captured images,
                # which we never request.
                if isinstance(message, str) and "multibody_sim_loaded" in message:
                    server._loaded.set()

            def on_close(self) -> None:
                with server._lock:
                    server._clients.discard(self)

        self._app = tornado_web.Application(
            [(r"/", Page), (r"/index\.html", Page), (r"/main\.min\.js", ViewerScript), (r"/ws", Commands)],
            websocket_max_message_size=1 << 20,
            log_function=lambda handler: None,  # no access log on the user's terminal
        )
        self._thread = threading.Thread(target=self._serve, name="multibody-sim meshcat server", daemon=True)
        self._thread.start()
        self._started.wait()

    def _serve(self) -> None:
        httpserver = require("tornado.httpserver", "the meshcat viewer")
        ioloop = require("tornado.ioloop", "the meshcat viewer")
        asyncio.set_event_loop(asyncio.new_event_loop())
        loop = self._loop = ioloop.IOLoop.current()
        self._http = httpserver.HTTPServer(self._app)
        self._http.add_sockets(self._sockets)
        loop.add_callback(self._started.set)
        loop.start()
        # Writes still queued for pages that are gone: cancel them rather than leave them pending.
        pending = asyncio.all_tasks(loop.asyncio_loop)
        for task in pending:
            task.cancel()
        loop.asyncio_loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
        loop.close(all_fds=True)

    # ---- commands -------------------------------------------------------------------------------------
    def send(self, command: dict[str, Any]) -> None:
        """Apply a meshcat command to the kept scene and forward it to every open page."""
        message = pack(command)
        kind, path = command["type"], command.get("path", "")
        with self._lock:
            if kind == "delete":
                prefix = path.rstrip("/") + "/"
                for key in [k for k in self._scene if len(k) > 1 and (k[1] == path or k[1].startswith(prefix))]:
                    del self._scene[key]
            elif kind == "set_object":
                self._scene[("object", path)] = message
            elif kind == "set_transform":
                self._scene[("transform", path)] = message
            elif kind == "set_property":
                self._scene[("property", path, command["property"])] = message
            elif kind == "set_animation":
                self._scene[("animation",)] = message
            else:  # our own commands: the last of each kind is what a new page needs
                self._scene[("custom", kind)] = message
            clients = list(self._clients)
        if clients:  # pages that connect later get it from the kept scene instead
            self._call(lambda: self._broadcast(message, clients))

    def _broadcast(self, message: bytes, clients: list[Any]) -> None:
        for client in clients:
            self._write(client, message)

    def _write(self, client: Any, message: bytes) -> bool:
        """Send one message to one page; a page that left (closed, reset, mid-message) is dropped quietly.

        tornado raises at once when it knows the connection is closed, and otherwise fails the write's future
        later: both are handled here, so that no traceback or "exception was never retrieved" reaches stderr.
        """
        try:
            done = client.write_message(message, binary=True)
        except Exception:  # WebSocketClosedError, StreamClosedError: the page closed meanwhile
            self._forget(client)
            return False
        done.add_done_callback(lambda future: self._after_write(client, future))
        return True

    def _after_write(self, client: Any, future: Any) -> None:
        if future.cancelled() or future.exception() is not None:  # retrieving it keeps asyncio quiet
            self._forget(client)

    def _forget(self, client: Any) -> None:
        with self._lock:
            self._clients.discard(client)

    def _call(self, function: Callable[[], None]) -> None:
        if self._loop is not None:
            self._loop.add_callback(function)

    @property
    def clients(self) -> int:
        """Number of pages connected now."""
        with self._lock:
            return len(self._clients)

    def wait_for_client(self, timeout: float | None = None) -> bool:
        """Block until a page has connected and applied the scene (True), or the timeout [s] ran out (False)."""
        return self._loaded.wait(timeout)

    def close(self) -> None:
        """Stop serving and release the port."""
        if self._loop is None:
            return
        loop, self._loop = self._loop, None

        def stop() -> None:
            self._http.stop()
            for client in list(self._clients):
                client.close()
            loop.stop()

        loop.add_callback(stop)
        self._thread.join(timeout=5)

    def __enter__(self) -> MeshcatServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _bind(netutil: Any, host: str, port: int | None) -> list[socket.socket]:
    """Listening sockets on exactly host:port (all of them the same port)."""
    candidates = list(DEFAULT_PORTS) + [0] if port is None else [port]
    last: OSError | None = None
    for candidate in candidates:
        try:
            return list(netutil.bind_sockets(candidate, address=host))
        except OSError as exc:
            last = exc
    raise OSError(f"cannot listen on {host}:{port if port is not None else '7000-7099'} ({last})")


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
