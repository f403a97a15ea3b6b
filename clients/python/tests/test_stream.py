"""The stream library (palpsim.stream) without a server: message checks, frame and brick
decoding, the deformed volume and its slices, statistics, newest-wins draining on a
bare XPUB, and Client.watch's argument checks. Brick values are compared exactly: int16
and float32 are exact in the volume's float32 and nothing is computed on them."""

from __future__ import annotations

import io
import time

import numpy as np
import pytest
import zmq

from palpsim.client import Client, Session, view_settings
from palpsim.proto import wire
from palpsim.stream import (DeformedVolume, MalformedMessage, SessionClosed, StreamClient,
                            StreamStats, UnknownSession, brick_topic, decode_brick,
                            decode_frame, frame_topic, parse_message, resolve_endpoint)
from test_view import (SID, GridSpec, frame_parts, jpeg, key_bricks, make_brick, notice_parts,
                       read_seq, seq_image, stream_message)

# ---------------------------------------------------------------------------------------
# Messages


def test_topics():
    assert frame_topic(0xAB) == b"frame.00000000000000ab"
    assert brick_topic(SID) == b"brick.1234abcd5678ef01"


@pytest.mark.parametrize("parts,words", [
    ([b"frame.x"], "1 ZeroMQ frames, expected 2"),
    ([b"frame.x", b"a", b"b"], "3 ZeroMQ frames, expected 2"),
    ([b"frame.x", b"\xff\xff\xff"], "does not parse"),
    ([b"frame.x", wire.StreamMessage(schema_version=2).SerializeToString()],
     "StreamMessage.schema_version = 2"),
    ([b"frame.x", wire.StreamMessage(schema_version=1).SerializeToString()],
     "StreamMessage.body"),
    ([b"brick.x", stream_message(frame=wire.Frame(frame_seq=1))], "StreamMessage.frame on topic"),
    ([b"frame.x", stream_message(brick=wire.Brick())], "StreamMessage.brick on topic"),
])
def test_malformed_messages_name_the_field(parts, words):
    with pytest.raises(MalformedMessage, match=words.replace(".", r"\.")):
        parse_message(parts)


def test_parse_message_accepts_a_frame():
    topic, msg = parse_message(frame_parts(SID, 3, 128, 64))
    assert topic == frame_topic(SID) and msg.frame.frame_seq == 3


def test_decode_frame():
    f = wire.Frame(frame_seq=9, width=320, height=180, jpeg=jpeg(seq_image(9, 320, 180)))
    rgb = decode_frame(f)
    assert rgb.shape == (180, 320, 3) and rgb.dtype == np.uint8 and read_seq(rgb) == 9
    with pytest.raises(MalformedMessage, match="Frame.jpeg of frame_seq 1: empty"):
        decode_frame(wire.Frame(frame_seq=1, width=320, height=180))
    with pytest.raises(MalformedMessage, match="not a readable JPEG"):
        decode_frame(wire.Frame(frame_seq=1, width=320, height=180, jpeg=b"\xff\xd8garbage"))
    from PIL import Image
    buf = io.BytesIO()
    Image.fromarray(seq_image(1, 320, 180)).save(buf, format="PNG")
    with pytest.raises(MalformedMessage, match="a PNG image, expected JPEG"):
        decode_frame(wire.Frame(frame_seq=1, width=320, height=180, jpeg=buf.getvalue()))
    with pytest.raises(MalformedMessage, match="Frame.width x height = 320x200"):
        decode_frame(wire.Frame(frame_seq=1, width=320, height=200, jpeg=f.jpeg))


# ---------------------------------------------------------------------------------------
# Bricks

ENCODINGS = [(wire.BRICK_INT16, np.int16), (wire.BRICK_FLOAT32, np.float32)]
COMPRESSIONS = [wire.COMPRESSION_NONE, wire.COMPRESSION_ZSTD]


def values(shape, dtype, seed=1):
    rng = np.random.default_rng(seed)
    if dtype == np.int16:
        return rng.integers(-32768, 32767, size=shape, endpoint=True).astype(np.int16)
    return (rng.standard_normal(shape) * 1000).astype(np.float32)


@pytest.mark.parametrize("encoding,dtype", ENCODINGS)
@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_decode_brick_round_trip(encoding, dtype, compression):
    grid = GridSpec()
    v = values((4, 5, 6), dtype)                           # (k, j, i)
    b = make_brick(SID, 1, grid, v, (2, 3, 4), encoding=encoding, compression=compression)
    got = decode_brick(b)
    assert got.shape == (4, 5, 6) and got.dtype == dtype
    assert np.array_equal(got, v)                          # the extremes of int16 included


def _broken(**change):
    b = make_brick(SID, 7, GridSpec(), values((4, 5, 6), np.int16), (2, 3, 4))
    for k, v in change.items():
        if k == "direction":
            del b.direction[:]
            b.direction.extend(v)
        else:
            setattr(b, k, v)
    return b


@pytest.mark.parametrize("change,words", [
    (dict(data=b"\x00" * 10), "Brick.data of brick_seq 7: 10 bytes, expected size_i*size_j*size_k*2 = 240"),
    (dict(raw_bytes=17), "Brick.raw_bytes = 17"),
    (dict(compression=wire.COMPRESSION_ZSTD, raw_bytes=240), "Brick.data of brick_seq 7: zstd"),
    (dict(compression=7), "Brick.compression = 7"),
    (dict(encoding=5), "Brick.encoding = 5"),
    (dict(lo_k=20), "Brick.lo_k + size_k = 20 + 4 of brick_seq 7 is past grid_size_k = 23"),
    (dict(grid_size_i=0), "an empty grid"),
    (dict(spacing_mm=0.0), "Brick.spacing_mm = 0.0"),
    (dict(direction=[1, 0, 0, 0, 1, 0, 0, 0]), "Brick.direction of brick_seq 7: 8 values"),
    (dict(lo_i=3), "Brick.origin_mm"),
    (dict(key=True, key_parts=2, key_part=2), "Brick.key_part = 2"),
    (dict(key=True, key_parts=2, key_part=0), "a key part is a slab of whole k-slices"),
])
def test_broken_bricks_name_the_field(change, words):
    with pytest.raises(MalformedMessage) as e:
        decode_brick(_broken(**change))
    assert words in str(e.value)


# ---------------------------------------------------------------------------------------
# The deformed volume

ROTATED = (0, -1, 0, 1, 0, 0, 0, 0, 1)  # columns: i along +y, j along -x, k along +z


@pytest.mark.parametrize("encoding,dtype", ENCODINGS)
def test_volume_key_voi_undeformed_exact(encoding, dtype):
    grid = GridSpec(size=(12, 9, 10), direction=ROTATED)
    image = values(grid.size[::-1], dtype, 2)
    voi = values((3, 4, 5), dtype, 3)
    vol = DeformedVolume()
    key = key_bricks(SID, grid, image, 3, encoding=encoding)
    for b in key[:2]:
        vol.apply(b)
    assert not vol.complete
    # a VOI brick while the key is half there, then the rest of the key: J is still the
    # key with the VOI over it (the box is redone over the slab that came later)
    vol.apply(make_brick(SID, 9, grid, voi, (1, 2, 6), encoding=encoding))
    vol.apply(key[2])
    assert vol.complete and vol.key_parts == 3 and vol.deformed
    want = image.astype(np.float32)
    want[6:9, 2:6, 1:6] = voi
    assert np.array_equal(vol.volume, want)
    # a newer VOI elsewhere: the old box is I again
    vol.apply(make_brick(SID, 10, grid, voi[:2], (0, 0, 0), encoding=encoding))
    want = image.astype(np.float32)
    want[0:2, 0:4, 0:5] = voi[:2]
    assert np.array_equal(vol.volume, want)
    # undeformed: J = I everywhere
    vol.apply(make_brick(SID, 11, grid, np.zeros((0, 0, 0)), encoding=encoding, deformed=False))
    assert np.array_equal(vol.volume, image.astype(np.float32)) and not vol.deformed
    assert vol.voi_bricks == 3 and vol.key_bytes == image.nbytes


def test_new_key_drops_the_voi_and_mixed_encodings():
    grid = GridSpec(size=(6, 5, 4))
    image = values(grid.size[::-1], np.int16, 4)
    vol = DeformedVolume()
    for b in key_bricks(SID, grid, image, 2):
        vol.apply(b)
    voi = values((2, 2, 2), np.float32, 5)
    vol.apply(make_brick(SID, 3, grid, voi, (1, 1, 1), encoding=wire.BRICK_FLOAT32,
                         compression=wire.COMPRESSION_ZSTD))
    assert vol.volume[1, 1, 1] == voi[0, 0, 0]             # float32 VOI over an int16 key
    image2 = image + 1
    for b in key_bricks(SID, grid, image2, 2, key_id=2, first_seq=4):
        vol.apply(b)
    assert vol.key_id == 2 and not vol.deformed
    assert np.array_equal(vol.volume, image2.astype(np.float32))


def test_volume_refuses_bricks_that_do_not_fit():
    grid = GridSpec(size=(6, 5, 4))
    vol = DeformedVolume()
    for b in key_bricks(SID, grid, values(grid.size[::-1], np.int16), 2):
        vol.apply(b)
    other = GridSpec(size=(6, 5, 5))
    with pytest.raises(MalformedMessage, match="not the grid of key 1"):
        vol.apply(make_brick(SID, 5, other, values((1, 1, 1), np.int16), (0, 0, 0)))
    b = key_bricks(SID, grid, values(grid.size[::-1], np.int16), 2)[0]
    b.key_parts = 3
    with pytest.raises(MalformedMessage, match="Brick.key_parts = 3 of key 1 part 0"):
        vol.apply(b)


def test_slices_through_a_point_on_a_rotated_grid():
    grid = GridSpec(size=(12, 9, 10), spacing_mm=1.5, origin_mm=(10.0, -5.0, 3.0), direction=ROTATED)
    image = values(grid.size[::-1], np.float32, 6)
    vol = DeformedVolume()
    for b in key_bricks(SID, grid, image, 4, encoding=wire.BRICK_FLOAT32):
        vol.apply(b)
    p = grid.box_origin((7, 2, 4))                        # voxel (i, j, k) = (7, 2, 4)
    assert vol.point_to_voxel(p + 0.4) == (7, 2, 4)       # nearest voxel (0.4 mm < half a voxel)
    s = vol.slices(p)
    assert s.index == (7, 2, 4)
    np.testing.assert_allclose(s.point_mm, p, atol=1e-12)
    assert np.array_equal(s.axial, image[4].astype(np.float32))          # [j, i]
    assert np.array_equal(s.coronal, image[:, 2, :].astype(np.float32))  # [k, i]
    assert np.array_equal(s.sagittal, image[:, :, 7].astype(np.float32))  # [k, j]
    assert vol.point_to_voxel((1e4, -1e4, 1e4))[2] == 9    # clamped into the grid
    # default point: the grid centre without a VOI, the VOI's centre with one
    assert vol.slices().index == (6, 4, 4)   # centre (5.5, 4, 4.5): np.rint rounds halves to even
    vol.apply(make_brick(SID, 9, grid, values((3, 3, 3), np.float32), (1, 2, 3),
                         encoding=wire.BRICK_FLOAT32))
    assert vol.slices().index == (2, 3, 4)


# ---------------------------------------------------------------------------------------
# Statistics


def test_stats_gaps_fps_and_latency_percentiles():
    st = StreamStats()
    # (frame_seq, pose_seq): gaps after 2 (3, 4) and 6 (7, 8, 9); frame 11 shows no pose yet
    frames = [(1, 1), (2, 2), (5, 5), (6, 6), (10, 10), (11, 0)]
    for i, (seq, pose) in enumerate(frames):
        st.note_frame(wire.Frame(frame_seq=seq, pose_seq=pose,
                                 pose_to_frame_ms=float(seq) if pose else 0.0), now_s=100.0 + 0.1 * i)
    assert st.frames_received == 6 and st.frames_missed == 2 + 3 and st.last_frame_seq == 11
    assert st.fps == pytest.approx(10.0)                  # 5 intervals in 0.5 s
    # a frame without a pose has no latency: the percentiles are of 1, 2, 5, 6, 10 ms
    assert st.pose_to_frame_p50_ms == pytest.approx(5.0)
    assert st.pose_to_frame_p99_ms == pytest.approx(np.percentile([1, 2, 5, 6, 10], 99))
    st.note_frame(wire.Frame(frame_seq=11, pose_seq=11), now_s=100.6)
    assert st.frames_missed == 5                          # a repeated seq is no gap


# ---------------------------------------------------------------------------------------
# StreamClient on a bare XPUB


@pytest.fixture
def xpub():
    ctx = zmq.Context.instance()
    s = ctx.socket(zmq.XPUB)
    s.setsockopt(zmq.LINGER, 0)
    s.setsockopt(zmq.SNDHWM, 10000)  # no drops: these tests check the viewer's own drain
    s.setsockopt(zmq.XPUB_VERBOSE, 1)  # every subscription, repeated topics too (as the server)
    port = s.bind_to_random_port("tcp://127.0.0.1")
    yield s, f"tcp://127.0.0.1:{port}"
    s.close(0)


def _wait_subscribed(sock, n=1):
    """Waits for n subscriptions (skipping the unsubscriptions of closed SUBs)."""
    got = []
    while len(got) < n:
        assert sock.poll(5000), "no subscription within 5 s"
        ev = sock.recv()
        if ev[:1] == b"\x01":
            got.append(ev[1:])
    return got


def test_newest_wins_drain(xpub):
    sock, ep = xpub
    with StreamClient(ep, frame_topic=frame_topic(SID), session_id=SID, frame_rcvhwm=1000) as sc:
        _wait_subscribed(sock)
        for seq in range(1, 51):
            sock.send_multipart(frame_parts(SID, seq, 128, 64))
        time.sleep(0.5)  # all 50 are queued at the SUB: one drain takes them all
        u = sc.receive(2.0)
        assert u.frame.frame_seq == 50 and u.frames_skipped == 49
        st = sc.stats
        assert (st.frames_received, st.frames_delivered, st.frames_skipped, st.frames_missed) == \
            (50, 1, 49, 0)
        assert sc.receive(0.1) is None


def test_notice_after_data_raises_on_the_next_receive(xpub):
    sock, ep = xpub
    with StreamClient(ep, frame_topic=frame_topic(SID), session_id=SID, frame_rcvhwm=1000) as sc:
        _wait_subscribed(sock)
        sock.send_multipart(frame_parts(SID, 1, 128, 64))
        sock.send_multipart(notice_parts(frame_topic(SID), SID, "scene_changed", "new scene"))
        sock.send_multipart(notice_parts(frame_topic(SID), SID, "closed", "bye"))
        time.sleep(0.3)
        u = sc.receive(2.0)
        assert u.frame.frame_seq == 1 and [n.event for n in u.notices] == ["scene_changed"]
        with pytest.raises(SessionClosed, match="bye"):
            sc.receive(1.0)


def test_unknown_session_notice_and_foreign_session(xpub):
    sock, ep = xpub
    with StreamClient(ep, frame_topic=frame_topic(SID), brick_topic=brick_topic(SID),
                      session_id=SID) as sc:
        _wait_subscribed(sock, 2)  # two sockets, one subscription each
        sock.send_multipart(notice_parts(brick_topic(SID), SID, "unknown_session", "no such",
                                         code=wire.ERROR_UNKNOWN_SESSION))
        with pytest.raises(UnknownSession, match="no such") as e:
            sc.receive(2.0)
        assert e.value.code == wire.ERROR_UNKNOWN_SESSION
    with StreamClient(ep, frame_topic=frame_topic(SID), session_id=SID) as sc:
        _wait_subscribed(sock)
        parts = frame_parts(SID, 1, 128, 64)
        m = wire.StreamMessage()
        m.ParseFromString(parts[1])
        m.frame.session_id = 5
        sock.send_multipart([parts[0], m.SerializeToString()])
        with pytest.raises(MalformedMessage, match="Frame.session_id = 0000000000000005"):
            sc.receive(2.0)


def test_bricks_keep_every_key_part_and_the_newest_voi(xpub):
    sock, ep = xpub
    grid = GridSpec(size=(6, 5, 4))
    with StreamClient(ep, brick_topic=brick_topic(SID), session_id=SID) as sc:
        _wait_subscribed(sock)
        for b in key_bricks(SID, grid, values(grid.size[::-1], np.int16), 4):
            sock.send_multipart([brick_topic(SID), stream_message(brick=b)])
        for seq in (5, 6, 7):
            b = make_brick(SID, seq, grid, values((1, 1, 1), np.int16), (0, 0, 0))
            sock.send_multipart([brick_topic(SID), stream_message(brick=b)])
        time.sleep(0.3)
        u = sc.receive(2.0)
        assert [(b.key, b.brick_seq) for b in u.bricks] == [(True, 1), (True, 2), (True, 3),
                                                             (True, 4), (False, 7)]
        assert sc.stats.bricks_received == 3 and sc.stats.bricks_skipped == 2


def test_resolve_endpoint():
    assert resolve_endpoint("tcp://*:7422", "tcp://10.0.0.5:7420") == "tcp://10.0.0.5:7422"
    assert resolve_endpoint("tcp://0.0.0.0:7422", "tcp://host.lan:7420") == "tcp://host.lan:7422"
    assert resolve_endpoint("tcp://127.0.0.1:7422", "tcp://10.0.0.5:7420") == "tcp://127.0.0.1:7422"
    assert resolve_endpoint("ipc:///tmp/s.stream", "ipc:///tmp/s") == "ipc:///tmp/s.stream"


def test_session_pose_endpoint_resolved():
    # a server bound to every interface (a container's tcp://0.0.0.0:7420) names its pose
    # endpoint with the wildcard host; the session connects to the control address's host
    # (127.0.0.2: a loopback address no test server binds; nothing is sent)
    c = Client("tcp://127.0.0.2:9")
    s = Session(c, wire.OpenReply(session_id=5, pose_endpoint="tcp://0.0.0.0:9"))
    try:
        assert s.pose_endpoint == "tcp://127.0.0.2:9"
    finally:
        s._close_socket()
        c.close()


# ---------------------------------------------------------------------------------------
# Client.watch's arguments


def test_view_settings_sets_only_what_is_given():
    v = view_settings({"width": 320, "center_mm": (1, 2, 3), "show_tip": False})
    assert v.width == 320 and v.HasField("show_tip") and not v.show_tip
    assert not v.HasField("height") and not v.HasField("preset") and v.HasField("center_mm")
    with pytest.raises(ValueError, match="unknown field.*colour"):
        view_settings({"colour": 1})
    with pytest.raises(ValueError, match=r"view\.center_mm = \(1, 2\): 2 values, expected 3"):
        view_settings({"center_mm": (1, 2)})
    with pytest.raises(ValueError, match=r"view\.width = -1"):
        view_settings({"width": -1})


def test_watch_refuses_unknown_encodings_before_sending():
    from palpsim.client import Client
    with Client("tcp://127.0.0.1:1", timeout_s=0.1) as c:
        with pytest.raises(ValueError, match="brick_encoding = 'int8'"):
            c.watch(bricks=True, brick_encoding="int8")
        with pytest.raises(ValueError, match="compression = 'lz4'"):
            c.watch(bricks=True, compression="lz4")
