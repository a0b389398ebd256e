"""How the simulated radio's bytes travel between the drones' runtimes: a ``Transport`` endpoint per drone,
broadcast and non-blocking receive, nothing else (``runtime.comms.Radio`` applies the channel's range, loss and
latency around it). ``InProcessBus``: threads of one process; ``UdpTransport``: processes on loopback."""
from __future__ import annotations

import abc
import collections
import socket

_RECV_BUF = 2048
"""Receive buffer [bytes]: a datagram that fills it is oversized (the radio drops it by size)."""


class Transport(abc.ABC):
    """One drone's endpoint: broadcast bytes to every other endpoint, take received bytes one at a time."""

    @abc.abstractmethod
    def send(self, data: bytes | bytearray | memoryview) -> None:
        """Broadcast ``data`` (copied before returning)."""

    @abc.abstractmethod
    def recv(self) -> bytes | memoryview | None:
        """The next received message, or None when there is none (never blocks). A memoryview is valid
        until the next call."""

    def close(self) -> None:
        """Release the endpoint."""


class InProcessBus:
    """Endpoints that share one process (one thread per drone)."""

    def __init__(self, n: int) -> None:
        self.queues = [collections.deque() for _ in range(n)]
        self.endpoints = [_BusEndpoint(self, i) for i in range(n)]

    def endpoint(self, index: int) -> "Transport":
        return self.endpoints[index]


class _BusEndpoint(Transport):
    def __init__(self, bus: InProcessBus, index: int) -> None:
        self.bus = bus
        self.index = index
        self._inbox = bus.queues[index]

    def send(self, data: bytes | bytearray | memoryview) -> None:
        blob = bytes(data)
        for j, q in enumerate(self.bus.queues):
            if j != self.index:
                q.append(blob)  # deque.append/popleft are thread-safe

    def recv(self) -> bytes | None:
        try:
            return self._inbox.popleft()
        except IndexError:
            return None


class UdpTransport(Transport):
    """UDP datagrams on loopback: endpoint ``index`` is bound to ``ports[index]`` and sends to all others."""

    def __init__(self, index: int, ports: list[int], host: str = "127.0.0.1") -> None:
        self.index = index
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        try:
            self.sock.bind((host, ports[index]))
        except OSError as exc:
            self.sock.close()
            raise OSError(f"agent {index}: cannot bind UDP {host}:{ports[index]} ({exc}): pick other ports "
                          f"(free_udp_ports) or stop the process holding it") from None
        self.sock.setblocking(False)
        self.peers = [(host, p) for j, p in enumerate(ports) if j != index]
        self._buf = bytearray(_RECV_BUF)
        self._view = memoryview(self._buf)

    def send(self, data: bytes | bytearray | memoryview) -> None:
        for peer in self.peers:
            try:
                self.sock.sendto(data, peer)
            except OSError:  # a peer that is gone (ECONNREFUSED) or a full buffer is a lost message
                pass

    def recv(self) -> memoryview | None:
        try:
            n = self.sock.recv_into(self._buf)
        except (BlockingIOError, InterruptedError):
            return None
        except OSError:  # ICMP port unreachable from an earlier send surfaces here on Linux
            return None
        return self._view[:n] if n < _RECV_BUF else self._view  # a full buffer: oversized, caught by size

    def close(self) -> None:
        self.sock.close()


def free_udp_ports(n: int, host: str = "127.0.0.1") -> list[int]:
    """``n`` loopback UDP ports that were free a moment ago."""
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
    try:
        for s in socks:
            s.bind((host, 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()
