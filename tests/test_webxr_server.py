"""The WebXR page's server without a browser: loopback by default, the page and nothing else
over HTTP, hand messages through a WebSocket to validated frames on the calling thread
(malformed ones counted and dropped, the connection kept), twin messages out, one driving
page, clean stop; the self-signed certificate for a LAN host; the teleop options."""

from __future__ import annotations

import json
import shutil
import ssl
import subprocess
import time
import urllib.error
import urllib.request
from urllib.parse import urlsplit, urlunsplit

import numpy as np
import pytest
from waiting import HANG_GUARD_S, wait_until
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from beavr_sim.headset.layouts import LAYOUTS
from beavr_sim.headset.sources import WebXRSource
from beavr_sim.headset.validation import StreamValidator
from beavr_sim.headset.webxr_protocol import encode_hands
from beavr_sim.headset.webxr_server import WebXRConfig, WebXRServer
from beavr_sim.headset.webxr_tls import ensure_certificate
from beavr_sim.naming import UnknownNameError
from beavr_sim.wire.access import SessionToken
from beavr_sim.wire.hand import N_JOINTS
from beavr_sim.wire.ports import PortConfig

T_MS = 1.7e12


def _hand() -> np.ndarray:
    rng = np.random.default_rng(0)
    canonical = np.array([0.3, 0.0, 1.1]) + rng.uniform(-0.09, 0.09, size=(N_JOINTS, 3))
    return LAYOUTS["webxr25"].from_canonical(canonical)


def _ws_url(server: WebXRServer) -> str:
    """The WebSocket URL the page opens from the printed URL (its ``?token=`` carried over)."""
    parts = urlsplit(server.url)
    return urlunsplit((parts.scheme.replace("http", "ws", 1), parts.netloc, "/ws", parts.query, ""))


def _take(server: WebXRServer, n: int, timeout_s: float = HANG_GUARD_S) -> list:
    frames, end = [], time.monotonic() + timeout_s
    while len(frames) < n and time.monotonic() < end:
        frames += server.take(0.1)
    return frames


@pytest.fixture
def server():
    s = WebXRServer(WebXRConfig(port=0), validator=StreamValidator())
    yield s
    s.close()


def test_defaults_bind_loopback_plain_http_on_the_configured_port():
    config = WebXRConfig()
    assert config.host == "127.0.0.1" and config.port == PortConfig().webxr == 8443
    assert not config.use_tls
    assert WebXRConfig(host="192.168.1.20").use_tls and WebXRConfig(host="0.0.0.0").use_tls
    assert not WebXRConfig(host="192.168.1.20", tls="off").use_tls
    with pytest.raises(ValueError, match=r"0\.0\.0\.0"):
        WebXRConfig(host="*")
    with pytest.raises(ValueError, match="IPv4"):
        WebXRConfig(host="300.1.2.3")
    with pytest.raises(ValueError, match=r"0\.\.65535"):
        WebXRConfig(port=70000)
    with pytest.raises(UnknownNameError, match="auto"):
        WebXRConfig(tls="yes")


def test_serves_the_page_bound_to_loopback_and_nothing_else(server):
    assert server._thread.is_alive()
    assert server.url.startswith("http://127.0.0.1:")
    with urllib.request.urlopen(server.url, timeout=5) as r:
        page = r.read().decode()
        assert r.headers["Content-Type"].startswith("text/html")
        assert "default-src 'self'" in r.headers["Content-Security-Policy"]
    assert ">Start</button>" in page and "webxr.js" in page
    for name in ("webxr.js", "twin_gl.js"):
        with urllib.request.urlopen(server.url + name, timeout=5) as r:
            assert r.headers["Content-Type"].startswith("text/javascript")
            script = r.read().decode()
            assert "http://" not in script and "https://" not in script  # nothing fetched
    for path in ("nope.js", "../webxr_server.py", "%2e%2e/webxr_server.py"):
        with pytest.raises(urllib.error.HTTPError) as info:
            urllib.request.urlopen(server.url + path, timeout=5)
        assert info.value.code == 404
    with pytest.raises(urllib.error.HTTPError) as info:  # a page from another site
        urllib.request.urlopen(
            urllib.request.Request(_ws_url(server).replace("ws", "http", 1), headers={
                "Origin": "http://evil.example", "Connection": "Upgrade", "Upgrade": "websocket",
            }),
            timeout=5,
        )  # fmt: skip
    assert info.value.code == 403


def test_hands_become_validated_frames_and_bad_messages_are_counted(server):
    validator = server.validator
    hand = _hand()
    with connect(_ws_url(server)) as ws:
        assert json.loads(ws.recv())["type"] == "welcome"
        for i in range(3):
            ws.send(encode_hands(T_MS + 10 * i, {"right": hand, "left": None}, seq=i))
        frames = _take(server, 6)
        assert [f.side for f in frames] == ["right", "left"] * 3
        assert all(f.tracked.sum() == N_JOINTS - 1 for f in frames[::2])  # palm is derived
        assert not any(f.tracked.any() for f in frames[1::2])  # left: absent -> untracked
        ws.send("not json")
        ws.send(b"\x80\x04binary")  # a pickle's first bytes: never unpickled
        ws.send('{"v": 9, "type": "hands"}')
        ws.send(encode_hands(T_MS, {"right": hand}))  # older than the last: out of order
        ws.send(encode_hands(T_MS + 100, {"right": hand}))  # still fine afterwards
        frames = _take(server, 2)
        assert len(frames) == 2 and frames[0].t_source == (T_MS + 100) / 1e3
    assert dict(server.stats.rejected) == {"not_json": 1, "binary": 1, "unknown_version": 1}
    assert validator.rejected_by_reason == {
        "not_json": 1,
        "binary": 1,
        "unknown_version": 1,
        "out_of_order": 2,  # both sides of that message
    }
    assert validator.accepted == 8 and server.stats.hand_messages == 5


def test_one_page_drives_and_twin_messages_reach_every_page(server):
    hand = _hand()
    with connect(_ws_url(server)) as first, connect(_ws_url(server)) as second:
        for ws in (first, second):
            assert json.loads(ws.recv())["type"] == "welcome"
        first.send(encode_hands(T_MS, {"right": hand}))
        assert len(_take(server, 2)) == 2 and server.driving
        second.send(encode_hands(T_MS + 10, {"right": hand}))
        wait_until(lambda: server.stats.rejected["second_page"] == 1, "second page refused")
        assert server.take(0.1) == [] and server.stats.rejected["second_page"] == 1
        server.publish("twin", {"v": 1, "type": "twin", "t": 1.0, "pose": np.arange(3.0)})
        for ws in (first, second):
            msg = json.loads(ws.recv(timeout=5))
            assert msg["type"] == "twin" and msg["pose"] == [0.0, 1.0, 2.0]
    wait_until(lambda: not server.driving, "the driving page's close reached the server")
    # A page that connects later gets the latest twin message at once.
    with connect(_ws_url(server)) as late:
        assert [json.loads(late.recv(timeout=5))["type"] for _ in range(2)] == ["welcome", "twin"]


def test_the_scene_with_its_meshes_reaches_a_page_that_connects_later(server):
    import gymnasium as gym

    import beavr_sim  # noqa: F401
    from beavr_sim.headset.webxr_scene import TwinFeed

    env = gym.make("beavr_sim/Pour-v0").unwrapped
    env.reset(seed=0)
    try:
        feed = TwinFeed(server, env.render_model, env.data, info={"task": "Pour"})
        wait_until(lambda: "scene" in server._latest, "the server took the scene")
        with connect(_ws_url(server), max_size=None) as ws:
            assert json.loads(ws.recv(timeout=5))["type"] == "welcome"
            text = ws.recv(timeout=10)
    finally:
        env.close()
    scene = json.loads(text)
    assert scene["type"] == "scene" and scene["meshes"]
    assert len(scene["meshes"]) == len(feed.geometry.meshes)
    assert [e["faces"] for e in scene["meshes"]] == [e["faces"] for e in feed.geometry.meshes]
    # Sent once, as the page's first twin message: well past a twin update, under 2 MB.
    assert 20_000 < len(text) < 2_000_000


def test_wait_blocks_until_frames_arrive_and_close_stops_the_thread():
    source = WebXRSource(WebXRConfig(port=0), StreamValidator())
    try:
        t0 = time.monotonic()
        assert source.wait(0.2) == [] and time.monotonic() - t0 >= 0.15
        with connect(_ws_url(source.server)) as ws:
            ws.recv()
            ws.send(encode_hands(T_MS, {"right": _hand(), "left": _hand()}))
            frames = source.wait(5.0)
            frames += source.poll(0.0)
        assert [f.side for f in frames] == ["right", "left"]
        assert source.validates and source.real_time
    finally:
        source.close()
    assert not source.server._thread.is_alive()  # close() joins it, at most 5 s
    source.server.publish("twin", {})  # after close: ignored, no error


def test_port_in_use_is_a_clear_error(server):
    with pytest.raises(OSError, match="webxr-port"):
        WebXRServer(WebXRConfig(port=server.port))


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed")
def test_https_certificate_for_a_lan_host(tmp_path):
    cert, key = ensure_certificate("192.168.77.5", tmp_path)
    assert cert.parent == tmp_path and key.stat().st_mode & 0o077 == 0
    names = subprocess.run(
        ["openssl", "x509", "-in", str(cert), "-noout", "-ext", "subjectAltName"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "IP Address:192.168.77.5" in names and "DNS:localhost" in names
    assert ensure_certificate("192.168.77.5", tmp_path) == (cert, key)  # cached
    mtime = cert.stat().st_mtime_ns
    ensure_certificate("192.168.77.5", tmp_path)
    assert cert.stat().st_mtime_ns == mtime
    ensure_certificate("10.0.0.9", tmp_path)  # another address: made again, naming both
    names = subprocess.run(
        ["openssl", "x509", "-in", str(cert), "-noout", "-ext", "subjectAltName"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "192.168.77.5" in names and "10.0.0.9" in names
    # Served over HTTPS (forced on loopback here, so the test needs no LAN address).
    server = WebXRServer(WebXRConfig(port=0, tls="on", cert_dir=tmp_path))
    try:
        assert server.url.startswith("https://127.0.0.1:")
        context = ssl.create_default_context(cafile=str(cert))
        with urllib.request.urlopen(server.url, context=context, timeout=5) as r:
            assert b"Start" in r.read()
        with connect(_ws_url(server), ssl=context) as ws:
            assert json.loads(ws.recv())["type"] == "welcome"
    finally:
        server.close()


def test_teleop_options_for_the_webxr_source():
    from beavr_sim.teleop.__main__ import build_parser
    from beavr_sim.teleop.session import SessionOptions

    args = build_parser().parse_args(["--task", "pour", "--source", "webxr"])
    options = SessionOptions.from_args(args)
    assert options.source == "webxr" and options.clock == "real"
    assert options.webxr_config() == WebXRConfig()
    args = build_parser().parse_args(
        ["--task", "pour", "--source", "webxr", "--webxr-host", "0.0.0.0", "--webxr-port", "9443"]
    )
    options = SessionOptions.from_args(args)
    config = options.webxr_config()
    assert (config.host, config.port, config.use_tls) == ("0.0.0.0", 9443, True)
    assert config.token.required and config.token == options.webxr_config().token  # one token
    given = build_parser().parse_args(["--task", "pour", "--source", "webxr", "--token", "T0k"])
    assert SessionOptions.from_args(given).webxr_config().token == SessionToken("T0k", True)
    with pytest.raises(ValueError, match="may not contain"):
        SessionOptions(task="pour", source="webxr", token="a b")
    # the twin drawn on the page across processes too (tests/test_stages.py runs it)
    assert not SessionOptions(task="pour", source="webxr", multiprocess=True).headless
    with pytest.raises(ValueError, match="IPv4"):
        SessionOptions(task="pour", source="webxr", webxr_host="1.2.3.999")
    with pytest.raises(UnknownNameError, match="webxr"):
        SessionOptions(task="pour", source="webxrr")


def test_token_is_off_on_loopback_and_on_elsewhere_or_when_given():
    assert not WebXRConfig().token.required
    assert WebXRConfig(host="0.0.0.0", port=0).token.required
    assert WebXRConfig(host="192.168.1.20", port=0).token.required
    forced = SessionToken.for_host("127.0.0.1", "given-token")
    assert forced.required and forced.check("given-token") is None
    assert forced.check("given-tokeN") == "bad_token" and forced.check(None) == "no_token"
    with pytest.raises(ValueError, match="may not contain"):
        SessionToken("a&b", True)


def test_websocket_without_the_session_token_is_refused_at_the_handshake():
    token = SessionToken.for_host("127.0.0.1", "s3cret-T0ken")
    server = WebXRServer(WebXRConfig(port=0, token=token), validator=StreamValidator())
    try:
        assert server.url.endswith("/?token=s3cret-T0ken")
        bare = _ws_url(server).split("?")[0]
        with pytest.raises(InvalidStatus) as no_token:
            connect(bare)
        assert no_token.value.response.status_code == 401
        with pytest.raises(InvalidStatus) as bad_token:
            connect(bare + "?token=s3cret-T0kem")
        assert bad_token.value.response.status_code == 403
        assert dict(server.stats.rejected) == {"no_token": 1, "bad_token": 1}
        assert server.refused_connections() == {"no_token": 1, "bad_token": 1}
        assert server.take(0.0) == [] and not server.driving
        with connect(_ws_url(server)) as ws:  # the printed URL's token: frames drive the twin
            assert json.loads(ws.recv())["type"] == "welcome"
            ws.send(encode_hands(T_MS, {"right": _hand(), "left": None}, seq=0))
            assert len(_take(server, 2)) == 2
    finally:
        server.close()


def test_refused_handshakes_are_counted_in_the_session_summary():
    """A WebSocket refused for its token shows in the teleop summary's ``rejected_by_reason``
    (beside the frames' reasons); ``frames_rejected`` counts frames only."""
    from beavr_sim.teleop.session import SessionOptions, build_loop

    options = SessionOptions(
        task="pour", source="webxr", viser=False, headless=True, progress=False,
        webxr_port=0, token="s3cret-T0ken",
    )  # fmt: skip
    loop = build_loop(options)
    try:
        bare = _ws_url(loop.source.server).split("?")[0]
        for url in (bare, bare + "?token=wrong"):
            with pytest.raises(InvalidStatus):
                connect(url)
        summary = loop.summary(False)
        assert summary.rejected_by_reason == {"no_token": 1, "bad_token": 1}
        assert summary.frames_rejected == 0
    finally:
        loop.source.close()
        loop.twin.env.close()


def test_announce_prints_the_tokened_url_and_a_qr_code_only_with_a_token():
    import io

    from beavr_sim.teleop.announce import announce_webxr

    out = io.StringIO()
    announce_webxr("https://10.0.0.2:8443/?token=abc", SessionToken("abc", True), out)
    text = out.getvalue()
    assert "?token=abc" in text and "token is required" in text and text.count("\n") > 10
    out = io.StringIO()
    announce_webxr("http://127.0.0.1:8443/", SessionToken("abc", False), out)
    assert "no token on a loopback" in out.getvalue() and out.getvalue().count("\n") == 2


def test_a_webxr_session_streams_the_twins_camera_to_the_page_at_a_bounded_rate():
    """``--source webxr --camera-stream-hz 4``, no real camera: the twin's ``front`` reaches a
    page (a raw WebSocket client) as ``camera`` messages with the in-scene panel's placement,
    no faster than the rate asked."""
    import base64
    import io

    from PIL import Image

    from beavr_sim.bench.webxr import SessionThread
    from beavr_sim.teleop.session import SessionOptions
    from beavr_sim.workcell import TABLE_TOP_Z, TABLE_X

    rate_hz = 4.0
    options = SessionOptions(
        task="PickupBox", source="webxr", viser=False, headless=True, progress=False,
        webxr_port=0, camera_stream_hz=rate_hz,
    )  # fmt: skip
    sess = SessionThread(options)
    messages = []
    try:
        with connect(_ws_url(sess.server), max_size=None) as ws:
            connected = time.monotonic()
            deadline = connected + 60.0  # readiness: the first render makes its GL context
            # (a panel drawn before the twin's first pose, or rendered over dead_after_s after
            # it on a busy machine, is rightly NO SIGNAL: read on until a live one came)
            while len(messages) < 4 or all(m["state"] != "live" for m in messages):
                assert time.monotonic() < deadline, f"{len(messages)} camera messages arrived"
                msg = json.loads(ws.recv(timeout=60.0))
                if msg["type"] == "camera":
                    messages.append(msg)
    finally:
        sess.stop()
    assert sess.error is None, sess.error
    # Composed at most rate_hz per second (the server's clock: `t`; +1 for the limiter's phase).
    sent = [m["t"] for m in messages]
    assert sent == sorted(sent) and len(sent) - 1 <= rate_hz * (sent[-1] - sent[0]) + 1
    live = [m for m in messages if m["state"] == "live"]
    assert live and {m["name"] for m in messages} == {"front"}
    msg = live[-1]
    assert msg["label"].startswith("front: live, age") and msg["label"].endswith("(twin)")
    image = np.asarray(Image.open(io.BytesIO(base64.b64decode(msg["jpeg"]))))
    assert image.shape == (msg["height"], msg["width"], 3) == (480, 640, 3)
    assert image.std() > 10  # the scene, not a flat NO SIGNAL panel
    x, y, z = msg["panel"]["center"]  # beyond the table's far edge, above its top
    assert x > TABLE_X[1] and y == 0.0 and z > TABLE_TOP_Z and msg["panel"]["width_m"] > 0
