"""Transports off the caller's thread: UDP receiver, reconnecting TCP client, serial, replay."""

from __future__ import annotations

import errno
import socket
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from rigspace.runtime.live.buffer import BindingCounters, LiveBuffer
from rigspace.runtime.live.source_frame import DecodeCounters, SourceFrame
from rigspace.sdk.errors import RigspaceError

POLL_SECONDS = 0.1
"""How long a receiver blocks in one read before it checks whether it should stop."""
UDP_RECEIVE_BUFFER = 1 << 20
"""Kernel receive buffer for UDP sources, bytes: a flood overflows the kernel's bounded buffer
(the excess is lost there, and counted: `kernel_dropped`), never our memory."""
SO_MEMINFO = getattr(socket, "SO_MEMINFO", 55)
"""Linux's getsockopt for a socket's memory counters (<asm-generic/socket.h>; Python names it
on no version yet)."""
SK_MEMINFO_DROPS = 8
"""Index of the datagrams the kernel dropped for the socket in SO_MEMINFO's u32 array
(<linux/sock_diag.h>): the drops column of /proc/net/udp, read from the socket itself."""


class LiveSourceError(RigspaceError):
    """A live source cannot start: names the binding, its URL and the fix."""


class Source:
    """A decoder fed by a transport on its own thread, delivering frames into a LiveBuffer.

    `start(buffer)` opens what the source needs on the caller's thread (so a port in use or a
    missing device raises a LiveSourceError right there), then receives on a daemon thread.
    """

    def __init__(self, name: str, url: str, decoder: Any) -> None:
        self.name, self.url, self.decoder = name, url, decoder
        self.bones: tuple[str, ...] = decoder.bones
        self.space: str = decoder.space
        self.reconnects = 0
        self.error: str | None = None
        """The transport's latest problem (connection refused, device gone), for `probe`."""
        self.buffer: LiveBuffer | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._deliver_lock = threading.Lock()  # several reader threads share one decoder

    @property
    def label(self) -> str:
        return f"Live source {self.name!r} ({self.url})" if self.name else f"Live source {self.url}"

    def start(self, buffer: LiveBuffer) -> None:
        self.buffer = buffer
        self._open()
        for i, run in enumerate(self._loops()):
            thread = threading.Thread(
                target=run, name=f"rigspace-live-{self.name or 'source'}-{i}", daemon=True
            )
            thread.start()
            self._threads.append(thread)

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout)
        self._close()

    def __enter__(self) -> Source:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def counters(self, now: float | None = None) -> BindingCounters:
        assert self.buffer is not None, "start() the source first"
        return self.buffer.counters(
            now, self.decoder.counters, self.reconnects, self.kernel_dropped()
        )

    def kernel_dropped(self) -> int | None:
        """Data the kernel dropped before it was read; None: this transport cannot tell."""
        return None

    def _deliver(self, data: bytes, received: float, **kw: Any) -> None:
        buffer = self.buffer
        assert buffer is not None
        with self._deliver_lock:
            frames = self.decoder.feed(data, received, **kw)
            for frame in frames:
                buffer.push(frame, received)
        # Every read counts (a VMC bone bundle completes no frame but is most of the work).
        buffer.note_latency(time.monotonic() - received)

    # Subclasses: open resources (raise LiveSourceError), give the loops, close resources.
    def _open(self) -> None: ...

    def _loops(self) -> list:
        return []

    def _close(self) -> None: ...


class UdpSource(Source):
    """Receives datagrams on HOST:PORT (127.0.0.1 unless the URL names another address)."""

    def __init__(self, name: str, url: str, decoder: Any, host: str, port: int) -> None:
        super().__init__(name, url, decoder)
        self.host, self.port = host, port
        self.sock: socket.socket | None = None
        self._kernel_dropped: int | None = None
        """The last count read from the socket (kept once it is closed)."""

    @property
    def address(self) -> tuple[str, int]:
        """The bound address (the real port when the URL asked for port 0)."""
        assert self.sock is not None
        return self.sock.getsockname()[:2]

    def _open(self) -> None:
        try:
            family = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_DGRAM)[0][0]
            sock = socket.socket(family, socket.SOCK_DGRAM)
        except OSError as exc:
            raise LiveSourceError(
                f"{self.label}: host {self.host!r} does not resolve ({exc}).",
                "use an address of this machine, such as 127.0.0.1.",
            ) from None
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER)
            sock.bind((self.host, self.port))
        except OSError as exc:
            sock.close()
            if exc.errno == errno.EADDRINUSE:
                raise LiveSourceError(
                    f"{self.label}: UDP port {self.port} on {self.host} is in use by another "
                    "program.",
                    "stop the other receiver (another rigspace live, a VMC app's receiver) or "
                    "put a free port in the URL.",
                ) from None
            raise LiveSourceError(
                f"{self.label}: cannot listen on {self.host}:{self.port} ({exc.strerror}).",
                "use an address of this machine (127.0.0.1 by default) and a port above 1023.",
            ) from None
        sock.settimeout(POLL_SECONDS)
        self.sock = sock

    def _loops(self) -> list:
        return [self._run]

    def _run(self) -> None:
        sock = self.sock
        assert sock is not None
        # A decoder that keeps senders apart (VMC: each its own frames and clock) gets the
        # datagram's source address.
        by_sender = bool(getattr(self.decoder, "by_sender", False))
        while not self._stop.is_set():
            try:
                data, sender = sock.recvfrom(65536)
            except TimeoutError:
                continue
            except OSError as exc:
                self.error = str(exc)
                if self._stop.wait(POLL_SECONDS):
                    return
                continue
            if by_sender:
                self._deliver(data, time.monotonic(), sender=sender)
            else:
                self._deliver(data, time.monotonic())

    def kernel_dropped(self) -> int | None:
        """Datagrams the kernel dropped because the receive buffer was full, as it counts them
        for this socket (SO_MEMINFO: one getsockopt, the same counter as /proc/net/udp's drops
        column, current at every call; SO_RXQ_OVFL would only bring it with the next datagram
        queued, so the drops at the end of a burst would go unreported). None on a system
        without it. After stop(), the count read last."""
        sock = self.sock
        if sock is None or sock.fileno() < 0:
            return self._kernel_dropped
        try:
            info = sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, 4 * (SK_MEMINFO_DROPS + 1))
        except OSError:  # not Linux, or a kernel without SO_MEMINFO
            return self._kernel_dropped
        if len(info) >= 4 * (SK_MEMINFO_DROPS + 1):  # older kernels return fewer counters
            self._kernel_dropped = int.from_bytes(info[4 * SK_MEMINFO_DROPS :][:4], sys.byteorder)
        return self._kernel_dropped

    def _close(self) -> None:
        if self.sock is not None:
            self.kernel_dropped()  # the final count, reported after the socket is gone
            self.sock.close()


class TcpClientSource(Source):
    """Connects to HOST:PORT and reads; reconnects (every `retry` seconds) when the server goes."""

    def __init__(
        self, name: str, url: str, decoder: Any, host: str, port: int, retry: float = 0.5
    ) -> None:
        super().__init__(name, url, decoder)
        self.host, self.port, self.retry = host, port, retry
        self.connected = False

    def _loops(self) -> list:
        return [self._run]

    def _run(self) -> None:
        ever = False
        while not self._stop.is_set():
            try:
                sock = socket.create_connection((self.host, self.port), timeout=1.0)
            except OSError as exc:
                self.error = f"cannot connect to {self.host}:{self.port}: {exc}"
                self._stop.wait(self.retry)
                continue
            if ever:
                self.reconnects += 1
            ever, self.connected, self.error = True, True, None
            sock.settimeout(POLL_SECONDS)
            with sock:
                while not self._stop.is_set():
                    try:
                        data = sock.recv(65536)
                    except TimeoutError:
                        continue
                    except OSError as exc:
                        self.error = f"connection to {self.host}:{self.port} failed: {exc}"
                        break
                    if not data:
                        self.error = f"{self.host}:{self.port} closed the connection"
                        break
                    self._deliver(data, time.monotonic())
            self.connected = False
            with self._deliver_lock:
                self.decoder.reset()  # a half line from the old connection is not data
            self._stop.wait(self.retry)


class SerialSource(Source):
    """Reads one or more pyserial ports (any pyserial URL: a device, loop://, socket://...);
    port i feeds decoder channel i."""

    def __init__(self, name: str, url: str, decoder: Any, devices: Sequence[str], baud: int):
        super().__init__(name, url, decoder)
        self.devices, self.baud = tuple(devices), baud
        self.ports: list[Any] = []

    def _open(self) -> None:
        import serial

        for device in self.devices:
            try:
                self.ports.append(
                    serial.serial_for_url(device, baudrate=self.baud, timeout=POLL_SECONDS)
                )
            except (serial.SerialException, ValueError) as exc:
                self._close()
                raise LiveSourceError(
                    f"{self.label}: serial device {device!r} cannot be opened ({exc}).",
                    "plug the device in and check its path and permissions (the dialout group), "
                    "or use a pyserial URL such as loop:// to test without hardware.",
                ) from None

    def _loops(self) -> list:
        return [lambda i=i: self._run(i) for i in range(len(self.ports))]

    def _run(self, channel: int) -> None:
        port = self.ports[channel]
        while not self._stop.is_set():
            try:
                data = port.read(max(1, min(port.in_waiting, 65536)))
            except Exception as exc:  # a device unplugged mid-stream: report, keep trying
                self.error = f"{self.devices[channel]}: {exc}"
                if self._stop.wait(POLL_SECONDS):
                    return
                continue
            if data:
                self._deliver(data, time.monotonic(), channel=channel)

    def _close(self) -> None:
        for port in self.ports:
            port.close()


class DeviceFileSource(Source):
    """Reads a character device (a Linux evdev node such as /dev/input/event5) on a thread."""

    def __init__(self, name: str, url: str, decoder: Any, device: str) -> None:
        super().__init__(name, url, decoder)
        self.device = device
        self.fd: int | None = None

    def _open(self) -> None:
        import os

        try:
            self.fd = os.open(self.device, os.O_RDONLY | os.O_NONBLOCK)
        except OSError as exc:
            raise LiveSourceError(
                f"{self.label}: device {self.device} cannot be opened ({exc.strerror}).",
                "plug the controller in and check the path (ls /dev/input/by-id) and that you "
                "may read it (the input group).",
            ) from None

    def _loops(self) -> list:
        return [self._run]

    def _run(self) -> None:
        import os
        import select

        fd = self.fd
        assert fd is not None
        while not self._stop.is_set():
            ready, _, _ = select.select([fd], [], [], POLL_SECONDS)
            if not ready:
                continue
            try:
                data = os.read(fd, 4096)
            except BlockingIOError:
                continue
            except OSError as exc:  # unplugged
                self.error = f"{self.device}: {exc}"
                if self._stop.wait(POLL_SECONDS):
                    return
                continue
            if not data:  # end of a file or pipe: nothing more will come
                self.error = f"{self.device}: end of data"
                if self._stop.wait(POLL_SECONDS):
                    return
                continue
            self._deliver(data, time.monotonic())

    def _close(self) -> None:
        import os

        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


class ClipPlayer:
    """A decoded clip as a decoder-like object: bones, space, counters (no bytes to parse)."""

    def __init__(self, bones: tuple[str, ...], space: str) -> None:
        self.bones, self.space = bones, space
        self.counters = DecodeCounters()

    def reset(self) -> None: ...


class ReplaySource(Source):
    """Plays decoded frames (F, B, 4) at their own times, scaled by 1/speed, looping or not.

    `times` are seconds from the clip's start (a BVH's frames are evenly spaced, a recorded
    take's follow its time codes, gaps included). Timestamps keep increasing across loops, so
    the buffer sees one continuous stream.
    """

    def __init__(
        self,
        name: str,
        url: str,
        bones: tuple[str, ...],
        rotations: np.ndarray,
        root_positions: np.ndarray | None,
        times: np.ndarray,
        speed: float = 1.0,
        loop: bool = True,
        parents: tuple[int, ...] = (),
        meters_per_unit: float | None = None,
        native: bool = False,
        rest_positions: np.ndarray | None = None,
        blend: tuple[tuple[str, ...], np.ndarray] | None = None,
    ) -> None:
        super().__init__(name, url, ClipPlayer(bones, "local"))
        self.blend = blend
        """(names, (F, S) weights): a recorded take's blend shape weights, sent with each frame."""
        self.parents = parents
        """The clip's hierarchy (parent index per bone, -1 for roots), for retargeting."""
        self.rotations, self.root_positions = rotations, root_positions
        self.times = np.asarray(times, dtype=np.float64)
        self.speed, self.loop = speed, loop
        self.meters_per_unit = meters_per_unit
        """Units of the root positions, when the file says (a USD take's stage)."""
        self.native = native
        """True for a recorded take: its bones are a skeleton's own joints and rest pose."""
        self.rest_positions = rest_positions
        """(B, 3) joint positions in the clip's rest pose (a BVH's), for rest alignment."""
        self.finished = threading.Event()

    def _loops(self) -> list:
        return [self._run]

    def _run(self) -> None:
        buffer = self.buffer
        assert buffer is not None
        counters = self.decoder.counters
        count = len(self.rotations)
        steps = np.diff(self.times)
        # One loop lasts the clip plus one typical frame (the last frame is shown that long).
        period = self.times[-1] - self.times[0] + (float(np.median(steps)) if count > 1 else 0.1)
        indices = np.arange(len(self.bones), dtype=np.int64)
        start = time.monotonic()
        n = 0
        while not self._stop.is_set():
            i = n % count
            if n and i == 0 and not self.loop:
                break
            clip_time = (n // count) * period + self.times[i] - self.times[0]
            due = clip_time / self.speed
            wait = start + due - time.monotonic()
            if wait > 0 and self._stop.wait(wait):
                break
            root = None if self.root_positions is None else self.root_positions[i]
            received = time.monotonic()
            weights = None
            if self.blend is not None:
                weights = dict(zip(self.blend[0], map(float, self.blend[1][i]), strict=True))
            buffer.push(SourceFrame(0, due, indices, self.rotations[i], root, weights), received)
            buffer.note_latency(time.monotonic() - received)
            counters.packets += 1
            counters.frames += 1
            counters.samples += len(indices)
            n += 1
        self.finished.set()
