"""The socket side: a MAVLink endpoint chosen by a pymavlink-style connection string.

Supported: ``udpin:HOST:PORT`` (also ``udp:``; bind, reply to the last sender),
``udpout:HOST:PORT`` (send to HOST:PORT), ``tcpin:HOST:PORT`` (listen, one client at a time)
and ``tcp:HOST:PORT`` (connect out). Port 0 binds an ephemeral port (see ``local_address``).

The sockets are written here rather than taken from ``mavutil.mavlink_connection`` because
pymavlink binds UDP with SO_REUSEADDR, which would hide a busy port instead of reporting it,
and because fault injection needs each datagram on its own. Everything is non-blocking:
``recv_all`` returns what has arrived and never waits. A stream client's bytes that arrive in the
same read as its close are dropped (counted in ``lost_on_close_bytes``), as ArduPilot never parses
them as that client's.
"""

from __future__ import annotations

import errno
import socket
from dataclasses import dataclass

_RECV_BYTES = 65535


class ConnectionStringError(ValueError):
    """The connection string cannot be understood."""


class PortInUseError(OSError):
    """The endpoint's port is already bound by another program."""


@dataclass(frozen=True)
class Address:
    kind: str  # udpin, udpout, tcpin, tcp
    host: str
    port: int


def parse_connection_string(text: str) -> Address:
    parts = text.strip().split(":")
    if len(parts) != 3:
        raise ConnectionStringError(
            f"bad connection string {text!r}: expected KIND:HOST:PORT, e.g. udpin:127.0.0.1:14551"
        )
    kind, host, port_text = parts
    kind = {"udp": "udpin"}.get(kind, kind)
    if kind not in ("udpin", "udpout", "tcpin", "tcp"):
        raise ConnectionStringError(
            f"bad connection string {text!r}: kind must be udpin, udp, udpout, tcpin or tcp"
        )
    try:
        port = int(port_text)
    except ValueError:
        raise ConnectionStringError(
            f"bad connection string {text!r}: port {port_text!r} is not a number"
        ) from None
    if not 0 <= port <= 65535 or (port == 0 and kind in ("udpout", "tcp")):
        raise ConnectionStringError(f"bad connection string {text!r}: port out of range")
    if not host:
        raise ConnectionStringError(f"bad connection string {text!r}: empty host")
    return Address(kind, host, port)


def _bind(sock: socket.socket, addr: Address, text: str) -> None:
    try:
        sock.bind((addr.host, addr.port))
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise PortInUseError(exc.errno, f"cannot bind {text}: address already in use") from exc
        raise OSError(exc.errno, f"cannot bind {text}: {exc.strerror}") from exc


class Endpoint:
    """One MAVLink link: datagrams (UDP) or chunks of a byte stream (TCP) in, bytes out."""

    def __init__(self, text: str) -> None:
        self.text = text
        self.address = parse_connection_string(text)
        self._peer: tuple[str, int] | None = None
        self._client: socket.socket | None = None
        self.send_errors = 0
        self.disconnects = 0  # stream clients that closed (EOF or reset) or were replaced
        self.lost_on_close_bytes = 0  # a closing stream client's bytes that were never parsed
        a = self.address
        if a.kind in ("udpin", "udpout"):
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            if a.kind == "udpin":
                _bind(self._sock, a, text)  # no SO_REUSEADDR: a busy port must fail loudly
            else:
                self._peer = (a.host, a.port)
        elif a.kind == "tcpin":
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # TIME_WAIT only
            _bind(self._sock, a, text)
            self._sock.listen(1)
        else:  # tcp client
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            try:
                self._sock.connect((a.host, a.port))
            except OSError as exc:
                self._sock.close()
                raise OSError(exc.errno, f"cannot connect {text}: {exc.strerror}") from exc
            self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._client = self._sock
        self._sock.setblocking(False)

    @property
    def local_address(self) -> tuple[str, int]:
        host, port = self._sock.getsockname()[:2]
        return str(host), int(port)

    @property
    def is_stream(self) -> bool:
        return self.address.kind in ("tcpin", "tcp")

    @property
    def connected(self) -> bool:
        return self._peer is not None or self._client is not None

    def fileno(self) -> int:
        return (self._client or self._sock).fileno()

    def recv_all(self) -> list[bytes]:
        """Everything that has arrived, without waiting (one item per datagram or TCP chunk)."""
        if self.address.kind == "tcpin":
            self._accept()
        out: list[bytes] = []
        if self.address.kind in ("udpin", "udpout"):
            while True:
                try:
                    data, peer = self._sock.recvfrom(_RECV_BYTES)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:  # e.g. ICMP port unreachable reported on a UDP socket
                    continue
                if self.address.kind == "udpin":
                    self._peer = (str(peer[0]), int(peer[1]))  # reply to the last sender
                out.append(data)
            return out
        while self._client is not None:
            try:
                data = self._client.recv(_RECV_BYTES)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                data = b""
            if not data:  # peer closed (FIN, or a reset)
                # ArduPilot reads a stream between main loops and parses it in the next one; the bytes
                # of a client that is gone by then are never parsed as its own (see sitl/autopilot.py).
                self.lost_on_close_bytes += sum(len(c) for c in out)
                out = []
                self._drop_client()
                break
            out.append(data)
        return out

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self._sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            conn.setblocking(False)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._drop_client()  # a new client replaces the old one, as on a serial link
            self._client = conn

    def _drop_client(self) -> None:
        if self._client is not None:
            self.disconnects += 1
            if self._client is not self._sock:
                self._client.close()
        self._client = None

    def send(self, data: bytes) -> None:
        """Send without blocking; with nobody to send to, or a full buffer, the bytes are lost."""
        try:
            if self.address.kind in ("udpin", "udpout"):
                if self._peer is not None:
                    self._sock.sendto(data, self._peer)
            elif self._client is not None:
                self._client.send(data)
        except OSError:
            self.send_errors += 1

    def close(self) -> None:
        self._drop_client()
        self._sock.close()
