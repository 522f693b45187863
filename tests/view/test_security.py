"""The viewer serves its own assets and the opened scene only, and refuses bad requests with 4xx."""

from __future__ import annotations

import json
import socket
import struct

import pytest
from starlette.websockets import WebSocketDisconnect

from rigspace.runtime.view.server import MAX_MESSAGE, STATIC, parse_request
from tests.view.conftest import PREVIS


def test_page_and_assets_are_served_with_their_types(previs_client):
    page = previs_client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert '<script type="module" src="/static/app.js">' in page.text
    js = previs_client.get("/static/app.js")
    assert js.status_code == 200 and js.headers["content-type"].startswith("text/javascript")
    assert previs_client.get("/static/style.css").headers["content-type"].startswith("text/css")
    # Every asset the page imports is one the package ships: no CDN.
    for path in STATIC.glob("*.js"):
        assert "http://" not in path.read_text() and "https://" not in path.read_text()


@pytest.mark.parametrize(
    "url",
    [
        "/static/../scene.py",
        "/static/..%2fscene.py",
        "/static/%2e%2e/%2e%2e/pyproject.toml",
        "/static//etc/passwd",
        "/static/..\\server.py",
        "/static/",
        "/etc/passwd",
        "/samples/scenes/previs.usda",
    ],
)
def test_path_traversal_and_unknown_files_are_404(previs_client, url):
    response = previs_client.get(url)
    assert response.status_code == 404
    assert "import" not in response.text and "root:" not in response.text


def test_a_path_from_the_browser_is_never_opened(previs_client):
    # /api/prim takes prim paths of the opened stage only; a file path is no prim.
    for path in (str(PREVIS), "../../etc/passwd", "@/etc/passwd@", "", "World", "/World.foo"):
        response = previs_client.get("/api/prim", params={"path": path})
        assert response.status_code == 404, path


@pytest.mark.parametrize(
    ("params", "status"),
    [
        ({"path": "/World/Hero", "time": "nan"}, 400),
        ({"path": "/World/Hero", "time": "inf"}, 400),
        ({"path": "/World/Hero", "time": "soon"}, 400),
        ({"path": "/ab" * 350}, 400),
        ({"path": "/World/Nothing"}, 404),
    ],
)
def test_malformed_parameters_are_4xx(previs_client, params, status):
    assert previs_client.get("/api/prim", params=params).status_code == status


def test_bodies_methods_long_urls_and_foreign_hosts_are_refused(previs_client):
    assert previs_client.post("/api/tree", content=b"x").status_code == 405
    assert previs_client.put("/").status_code == 405
    big = previs_client.request("GET", "/api/tree", content=b"x" * 10)
    assert big.status_code == 413
    assert previs_client.get("/api/tree?" + "a" * 5000).status_code == 414
    # DNS rebinding: a page from another name resolving to 127.0.0.1 is not served.
    evil = previs_client.get("/api/tree", headers={"host": "evil.example:8765"})
    assert evil.status_code == 400
    assert previs_client.get("/api/tree", headers={"host": "localhost:8765"}).status_code == 200
    assert previs_client.get("/api/tree", headers={"host": "[::1]:8765"}).status_code == 200
    assert previs_client.get("/api/tree", headers={"host": "127.0.0.1.evil:80"}).status_code == 400
    odd = previs_client.get("/api/tree", headers={"content-length": "many"})
    assert odd.status_code == 400


def test_websocket_from_another_origin_is_refused(previs_client):
    with pytest.raises(WebSocketDisconnect) as denied:
        with previs_client.websocket_connect(
            "ws://127.0.0.1/ws", headers={"origin": "http://evil.example"}
        ):
            pass
    assert getattr(denied.value, "status_code", None) == 403


@pytest.mark.parametrize(
    ("message", "code"),
    [
        ("not json", 4400),
        (json.dumps({"op": "open", "path": "/etc/passwd"}), 4400),
        (json.dumps({"op": "frame", "time": "1"}), 4400),
        (json.dumps({"op": "frame", "time": 1, "map": "../../x"}), 4400),
        (json.dumps({"op": "frame", "time": 1, "camera": "/etc/passwd"}), 4400),
        (json.dumps({"op": "frame", "time": 1, "pad": "x" * MAX_MESSAGE}), 4413),
    ],
)
def test_malformed_and_oversized_messages_close_the_socket_with_4xx(previs_client, message, code):
    with previs_client.websocket_connect("ws://127.0.0.1/ws") as ws:
        ws.send_text(message)
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_bytes()
    assert closed.value.code == code


def test_binary_messages_are_refused(previs_client):
    with previs_client.websocket_connect("ws://127.0.0.1/ws") as ws:
        ws.send_bytes(b"\x00" * 8)
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_bytes()
    assert closed.value.code == 4400


def test_parse_request_accepts_a_good_request_only():
    good = parse_request(json.dumps({"op": "frame", "time": 3, "map": "depth"}), ["/Cam"])
    assert good["time"] == 3.0 and good["map"] == "depth" and good["quality"] == "auto"
    with pytest.raises(ValueError):
        parse_request(json.dumps({"op": "frame", "time": 1e400}), [])  # inf after parsing
    with pytest.raises(ValueError):
        parse_request(json.dumps({"op": "frame", "time": 1, "id": True}), [])


def _handshake(port: int, key: str = "dGhlIHNhbXBsZSBub25jZQ==") -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=20)
    sock.sendall(
        (
            f"GET /ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:
        head += sock.recv(1)
    assert head.startswith(b"HTTP/1.1 101"), head
    return sock


def _send_frame(sock: socket.socket, payload: bytes, opcode: int = 1) -> None:
    """A masked client frame, as RFC 6455 says a client sends."""
    mask = b"\x01\x02\x03\x04"
    n = len(payload)
    head = bytes([0x80 | opcode])
    if n < 126:
        head += bytes([0x80 | n])
    elif n < 65536:
        head += bytes([0x80 | 126]) + struct.pack(">H", n)
    else:
        head += bytes([0x80 | 127]) + struct.pack(">Q", n)
    sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))


def _read_frame(sock: socket.socket) -> tuple[int, bytes]:
    def exactly(n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = sock.recv(n - len(data))
            if not chunk:
                raise ConnectionError("closed")
            data += chunk
        return data

    b0, b1 = exactly(2)
    n = b1 & 0x7F
    if n == 126:
        n = struct.unpack(">H", exactly(2))[0]
    elif n == 127:
        n = struct.unpack(">Q", exactly(8))[0]
    return b0 & 0x0F, exactly(n)


def test_raw_websocket_frames_and_refusals_on_a_real_server(previs_served):
    _, url = previs_served
    port = int(url.rsplit(":", 1)[1].strip("/"))
    sock = _handshake(port)
    _send_frame(sock, json.dumps({"op": "frame", "id": 7, "time": 12, "quality": "full"}).encode())
    opcode, data = _read_frame(sock)
    while opcode != 2:  # text pushes may come first
        opcode, data = _read_frame(sock)
    length = struct.unpack(">I", data[:4])[0]
    header = json.loads(data[4 : 4 + length])
    assert header["id"] == 7 and header["time"] == 12 and header["quality"] == "full"
    assert data[4 + length : 4 + length + 2] == b"\xff\xd8"  # a JPEG
    assert header["report"]["characters"][0]["path"] == "/World/Hero"
    # An oversized message (64 KiB) is refused: close code 4413.
    _send_frame(sock, b"{" + b" " * 65536 + b"}")
    opcode, data = _read_frame(sock)
    while opcode != 8:
        opcode, data = _read_frame(sock)
    assert struct.unpack(">H", data[:2])[0] == 4413
    sock.close()
    # A handshake from a foreign origin is answered 403 before any upgrade.
    raw = socket.create_connection(("127.0.0.1", port), timeout=10)
    raw.sendall(
        (
            f"GET /ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
            "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
            "Sec-WebSocket-Version: 13\r\nOrigin: http://evil.example\r\n\r\n"
        ).encode()
    )
    assert raw.recv(64).startswith(b"HTTP/1.1 403")
    raw.close()


@pytest.mark.parametrize(
    "weights",
    [
        [1, 2],
        {"/World/Hero": [0.5]},
        {"/World/Hero": {"jawOpen": "open"}},
        {"/World/Hero": {"jawOpen": True}},
        {"/World/Hero": {"jawOpen": 3.0}},
        {"/World/Hero": {f"s{k}": 0.1 for k in range(300)}},
    ],
)
def test_a_request_with_malformed_blend_shape_weights_is_refused(weights):
    with pytest.raises(ValueError, match="weight"):
        parse_request(json.dumps({"op": "frame", "time": 1, "weights": weights}), [])
    good = parse_request(
        json.dumps({"op": "frame", "time": 1, "weights": {"/World/Hero": {"jawOpen": 0.25}}}), []
    )
    assert good["weights"] == {"/World/Hero": {"jawOpen": 0.25}}


def test_a_requests_control_values_join_its_weights_and_bad_ones_are_refused():
    """The control sliders' values (docs/point_caches.md) travel as `controls`, in the
    control's own units (not the blend shapes' [-2, 2]), and are merged with the character's
    weights for the engine; a value that is not a finite number within the bound is refused."""
    message = {"op": "frame", "time": 1, "weights": {"/World/Hero": {"jawOpen": 0.25}},
               "controls": {"/World/Hero": {"twist": -45.0}, "/World/Other": {"bulge": 1}}}  # fmt: skip
    good = parse_request(json.dumps(message), [])
    assert good["weights"] == {
        "/World/Hero": {"jawOpen": 0.25, "twist": -45.0},
        "/World/Other": {"bulge": 1.0},
    }
    for controls in ([1], {"/World/Hero": {"twist": "left"}}, {"/World/Hero": {"twist": 1e9}}):
        with pytest.raises(ValueError, match="control"):
            parse_request(json.dumps({"op": "frame", "time": 1, "controls": controls}), [])
    many = {"/World/Hero": {f"c{k}": 0.1 for k in range(300)}}
    with pytest.raises(ValueError, match="at most 256"):
        parse_request(json.dumps({"op": "frame", "time": 1, "controls": many}), [])
