"""Run the labeling application in a background thread beside training."""

import ipaddress
import socket
import threading
import time
from typing import Optional

import uvicorn

from sb3_hhp.label.app import create_app
from sb3_hhp.preferences.store import PreferenceStore

__all__ = ["LabelServer", "check_bind", "is_loopback"]


def is_loopback(host: str) -> bool:
    """Whether ``host`` names the local machine only (``localhost``, 127.0.0.0/8, ``::1``)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_bind(host: str, token: Optional[str]) -> None:
    """Refuse to serve beyond the local machine without a token.

    :param host: the address to bind
    :param token: the access token (``None`` for none)
    """
    if not isinstance(host, str) or not host:
        raise ValueError(f"host must be a non-empty string, got {host!r}")
    if not is_loopback(host) and not token:
        raise ValueError(
            f"Serving the labeling page on {host!r} exposes it beyond this machine: pass a token "
            "(--token / token=...) or bind 127.0.0.1"
        )


class LabelServer:
    """The labeling web page served by uvicorn in a daemon thread.

    :param store: the preference store to serve
    :param host: address to bind; anything but loopback requires ``token``
    :param port: TCP port, 0 picks a free one (read it back from :attr:`url`)
    :param token: access token required on every API call (see :func:`~sb3_hhp.label.app.create_app`)
    :param reply_window_s: seconds per question before the page answers CAN'T TELL (> 0)
    """

    def __init__(
        self,
        store: PreferenceStore,
        host: str = "127.0.0.1",
        port: int = 0,
        token: Optional[str] = None,
        reply_window_s: float = 5.0,
    ) -> None:
        check_bind(host, token)
        if not 0 <= int(port) <= 65535:
            raise ValueError(f"port must be in [0, 65535] (0 picks a free one), got {port}")
        self.store = store
        self.host = host
        self.port = int(port)
        self.token = token
        self.app = create_app(store, token=token, reply_window_s=reply_window_s)
        self._server: Optional[uvicorn.Server] = None
        self._thread: Optional[threading.Thread] = None
        self._socket: Optional[socket.socket] = None

    @property
    def url(self) -> str:
        """The page's address (with the token as query parameter when one is set); valid after :meth:`start`."""
        if self._socket is None:
            raise RuntimeError("LabelServer.url is known once start() has bound the port")
        host = self.host if self.host not in ("0.0.0.0", "::") else "127.0.0.1"
        if ":" in host:
            host = f"[{host}]"
        url = f"http://{host}:{self.port}/"
        return url + (f"?token={self.token}" if self.token else "")

    def start(self, timeout: float = 10.0) -> "LabelServer":
        """Bind the port and serve in a background thread; return once the server accepts connections.

        :param timeout: seconds to wait for the server to come up
        """
        if self._thread is not None:
            raise RuntimeError("LabelServer is running already")
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((self.host, self.port))
        self.port = sock.getsockname()[1]
        self._socket = sock
        config = uvicorn.Config(self.app, log_level="warning", access_log=False, lifespan="off")
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(
            target=self._server.run, kwargs={"sockets": [sock]}, name="sb3_hhp-label-server", daemon=True
        )
        self._thread.start()
        deadline = time.monotonic() + timeout
        while not self._server.started and self._thread.is_alive() and time.monotonic() < deadline:
            time.sleep(0.02)
        if not self._server.started:
            self.stop()
            raise RuntimeError(f"The labeling server did not start on {self.host}:{self.port} within {timeout} s")
        return self

    def stop(self, timeout: float = 10.0) -> None:
        """Stop serving and free the port (the store stays open)."""
        if self._server is not None:
            self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout)
        if self._socket is not None:
            self._socket.close()
        self._server = None
        self._thread = None

    def __enter__(self) -> "LabelServer":
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()
