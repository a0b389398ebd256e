"""A UDP relay between a client and the simulators that loses datagrams (the demo's ``--loss``)."""
from __future__ import annotations

import random
import selectors
import socket
import threading


class LossyRelay:
    """UDP relay between cflib and the simulators that drops datagrams with probability ``loss``."""

    def __init__(self, targets: list[int], loss: float, seed: int = 0, host: str = "127.0.0.1") -> None:
        self.loss = loss
        self.host = host
        self.targets = targets
        self._rng = random.Random(seed)
        self._sel = selectors.DefaultSelector()
        self._front: list[socket.socket] = []
        self._back: list[socket.socket] = []
        self._client: list[tuple[str, int] | None] = [None] * len(targets)
        self.ports: list[int] = []
        self.dropped = 0
        self.forwarded = 0
        for i, port in enumerate(targets):
            f = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            f.bind((host, 0))
            f.setblocking(False)
            b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            b.connect((host, port))
            b.setblocking(False)
            self._sel.register(f, selectors.EVENT_READ, (i, True))
            self._sel.register(b, selectors.EVENT_READ, (i, False))
            self._front.append(f)
            self._back.append(b)
            self.ports.append(f.getsockname()[1])
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="LossyRelay", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            for key, _ in self._sel.select(0.05):
                i, from_client = key.data
                while True:
                    try:
                        data, addr = key.fileobj.recvfrom(256)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:
                        break
                    if from_client:
                        self._client[i] = addr
                    if self._rng.random() < self.loss:
                        self.dropped += 1
                        continue
                    try:
                        if from_client:
                            self._back[i].send(data)
                        elif self._client[i] is not None:
                            self._front[i].sendto(data, self._client[i])
                        self.forwarded += 1
                    except OSError:
                        pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._sel.close()
        for s in self._front + self._back:
            s.close()
