from __future__ import annotations

import time

import numpy as np
import pytest

from beavr_sim.headset.quest_protocol import (
    MAX_PAYLOAD_BYTES,
    REASONS,
    KeypointParseError,
    ProtocolError,
    format_keypoints,
    parse_keypoints,
    parse_pause,
    parse_resolution,
)
from beavr_sim.naming import UnknownNameError
from beavr_sim.wire.hand import JOINT_INDEX, N_JOINTS, HandFrame


def random_frame(seed: int = 0, untracked=(3, 17)) -> HandFrame:
    rng = np.random.default_rng(seed)
    joints = rng.uniform(-0.8, 0.8, size=(N_JOINTS, 3))
    tracked = np.ones(N_JOINTS, dtype=bool)
    tracked[list(untracked)] = False
    joints[~tracked] = np.nan
    return HandFrame("right", 12.5, 12.5, joints, tracked)


def triples(values) -> str:
    return "|".join(",".join(v) for v in values)


VALID = format_keypoints(random_frame())
BODY = VALID[len("absolute:") : -1]


def test_round_trip_within_the_decimals():
    frame = random_frame()
    assert VALID.startswith("absolute:") and VALID.endswith(":")
    parsed = parse_keypoints(VALID.encode(), "right", t_receive=3.0)
    np.testing.assert_array_equal(parsed.tracked, frame.tracked)
    np.testing.assert_allclose(parsed.joints[frame.tracked], frame.joints[frame.tracked], atol=5e-6)
    assert np.isnan(parsed.joints[~frame.tracked]).all()
    assert parsed.t_source == parsed.t_receive == 3.0
    coarse = format_keypoints(frame, marker="relative", decimals=2)
    parsed = parse_keypoints(coarse, "left", 3.0, t_source=2.0, resolution="low", paused=True)
    assert (parsed.side, parsed.t_source, parsed.resolution, parsed.paused) == (
        "left",
        2.0,
        "low",
        True,
    )
    np.testing.assert_allclose(parsed.joints[frame.tracked], frame.joints[frame.tracked], atol=5e-3)
    err = np.abs(parsed.joints[frame.tracked] - frame.joints[frame.tracked]).max()
    assert err > 1e-4  # the decimals argument really rounds


def test_coordinates_are_converted_from_unity():
    values = [("0", "0", "0")] * N_JOINTS
    values[0] = ("0.1", "0.2", "0.3")  # wrist: Unity x right, y up, z forward
    values[JOINT_INDEX["index_tip"]] = ("-1.5E-02", "1e-3", ".25")
    frame = parse_keypoints(f"relative:{triples(values)}:", "right", 0.0)
    np.testing.assert_allclose(frame.position("wrist"), [0.3, -0.1, 0.2])
    np.testing.assert_allclose(frame.position("index_tip"), [0.25, 0.015, 0.001])
    assert frame.tracked.sum() == 2
    assert format_keypoints(frame).count("0.00000,0.00000,0.00000") == N_JOINTS - 2


def _german() -> str:
    return "absolute:" + BODY.replace(".", ",") + ":"  # C# in a de-DE locale


def _with_triple(i: int, text: str) -> str:
    parts = BODY.split("|")
    parts[i] = text
    return "absolute:" + "|".join(parts) + ":"


REJECTIONS = [
    (b"absolute:\xff\xfe:", "not_utf8", "UTF-8"),
    ("absolute:" + "1" * MAX_PAYLOAD_BYTES + ":", "too_long", "at most"),
    (b"x" * (MAX_PAYLOAD_BYTES + 1), "too_long", "bytes"),
    ("", "no_marker", "relative"),
    ("0.1,0.2,0.3|", "no_marker", "absolute"),
    (":" + BODY + ":", "no_marker", "relative"),
    ("Absolute:" + BODY + ":", "unknown_marker", "absolute"),
    ("absolute:" + BODY, "no_terminator", "end with ':'"),
    ("absolute:" + BODY + ":\n", "no_terminator", "end with ':'"),
    ("absolute:" + BODY.rsplit("|", 1)[0] + ":", "wrong_joint_count", "got 25"),
    ("absolute:" + BODY + "|0,0,0:", "wrong_joint_count", "got 27"),
    ("absolute::", "wrong_joint_count", "got 1"),
    (_with_triple(4, "0.1,0.2"), "wrong_triple", "joint 4 (thumb_distal)"),
    (_with_triple(4, "0.1,0.2,0.3,0.4"), "wrong_triple", "4 ','-separated"),
    (_german(), "comma_decimal", "decimal separator"),
    (_with_triple(9, "0.1,abc,0.3"), "not_a_number", "joint 9 (index_distal)"),
    (_with_triple(9, "0.1, 0.2,0.3"), "not_a_number", "' 0.2'"),
    (_with_triple(9, "0.1,0x10,0.3"), "not_a_number", "0x10"),
    (_with_triple(9, "0.1,1_0,0.3"), "not_a_number", "1_0"),
    (_with_triple(9, "0.1,\u0661.5,0.3"), "not_a_number", "joint 9"),  # Arabic-Indic digit
    (_with_triple(2, "NaN,0.1,0.1"), "non_finite", "'NaN'"),
    (_with_triple(2, "0.1,-Infinity,0.1"), "non_finite", "finite"),
    (_with_triple(2, "0.1,\u221e,0.1"), "non_finite", "finite"),
    (_with_triple(2, "0.1,1e999,0.1"), "non_finite", "overflows"),
    (_with_triple(25, "0.1,-10.5,0.1"), "too_far", "little_tip"),
    ("absolute:" + triples([("0", "0.0", "-0")] * N_JOINTS) + ":", "untracked", "0,0,0"),
]


@pytest.mark.parametrize(("payload", "reason", "fragment"), REJECTIONS)
def test_rejections(payload, reason, fragment):
    with pytest.raises(KeypointParseError) as info:
        parse_keypoints(payload, "right", 0.0)
    assert info.value.reason == reason
    assert fragment in str(info.value)


def test_every_keypoint_reason_is_exercised():
    assert {r for _, r, _ in REJECTIONS} == set(REASONS) - {"unknown_button"}


def test_comma_decimal_with_whole_numbers_and_swedish_minus():
    values = [("0,125", "1", "\u22120,5")] * N_JOINTS  # whole numbers keep 1 field each
    with pytest.raises(KeypointParseError) as info:
        parse_keypoints(f"absolute:{triples(values)}:", "right", 0.0)
    assert info.value.reason == "comma_decimal"


def test_protocol_error_reason_is_checked():
    with pytest.raises(UnknownNameError, match="not_utf8"):
        KeypointParseError("bogus", "x")
    assert issubclass(KeypointParseError, ProtocolError)
    assert issubclass(ProtocolError, ValueError)
    with pytest.raises(TypeError, match="bytes or str"):
        parse_keypoints(None, "right", 0.0)  # type: ignore[arg-type]


def test_fuzz_only_protocol_errors():
    rng = np.random.default_rng(7)
    payloads: list[bytes | str] = [VALID[:n] for n in range(len(VALID))]
    payloads += [
        bytes(rng.integers(0, 256, size=rng.integers(0, 700), dtype=np.uint8)) for _ in range(300)
    ]
    alphabet = "0123456789.,|:-+eE absolutrelativNaInfy\u2212\x00"
    for _ in range(1500):
        chars = list(VALID)
        for _ in range(rng.integers(1, 4)):
            chars[rng.integers(len(chars))] = alphabet[rng.integers(len(alphabet))]
        payloads.append("".join(chars))
    parsed = 0
    for payload in payloads:
        try:
            parse_keypoints(payload, "left", 1.0)
            parsed += 1
        except ProtocolError as exc:
            assert exc.reason in REASONS
    assert 0 < parsed < len(payloads)  # some mutations stay valid (digit -> digit)


def test_buttons():
    assert parse_resolution(b"High") == "high"
    assert parse_resolution("Low") == "low"
    assert parse_resolution(b"None") is None
    assert parse_pause(b"Low") is True
    assert parse_pause("High") is False
    for parse, payload in [
        (parse_resolution, b"high"),
        (parse_resolution, b"Medium"),
        (parse_pause, b"None"),
        (parse_pause, b"High\n"),
    ]:
        with pytest.raises(ProtocolError) as info:
            parse(payload)
        assert info.value.reason == "unknown_button"
        assert "expected one of" in str(info.value)
    with pytest.raises(ProtocolError) as info:
        parse_pause(b"\xc3")
    assert info.value.reason == "not_utf8"


def test_format_rejects_bad_arguments():
    frame = random_frame()
    with pytest.raises(UnknownNameError, match="absolute"):
        format_keypoints(frame, marker="abs")
    with pytest.raises(ValueError, match="decimals"):
        format_keypoints(frame, decimals=-1)
    far = HandFrame("right", 0.0, 0.0, np.full((N_JOINTS, 3), 11.0))
    with pytest.raises(ValueError, match=r"10\.0 m"):
        format_keypoints(far)


def test_parse_speed():
    payload = VALID.encode()
    n = 2000
    start = time.perf_counter()
    for _ in range(n):
        parse_keypoints(payload, "right", 0.0)
    per_message = (time.perf_counter() - start) / n
    print(f"parse_keypoints: {per_message * 1e6:.1f} us per message")
    assert per_message < 2e-3  # loose: a shared CI core; the headset sends ~2 x 90 per second
