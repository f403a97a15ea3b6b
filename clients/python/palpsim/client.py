"""Client library for palpsim-server (protocol: proto/PROTOCOL.md, schema proto/palpsim/wire.proto).

    with Client("tcp://127.0.0.1:7420") as c:
        with c.open_session("me") as s:
            r = s.pose((0.0, 120.0, 0.0), client_time_s=1.0)
            print(r.force_n, r.contact, r.depth_mm)

A Client owns a control socket (a DEALER to the address the server printed); each
Session owns a pose socket (a DEALER to the session's pose endpoint). ZeroMQ sockets
are not thread-safe: use one Client per thread. Refused requests raise ServerError
with the server's code and sentence; a server that does not answer within the
timeout raises ServerTimeout. Units: mm, N, s; points in the CT's physical space (LPS).

A server with keys (docs/security.md) needs `curve=CurveKeys.from_files(server_key,
client_key)`. A session belongs to the client that opened it: its CURVE key, else its
`client_token`, else its control connection (PROTOCOL.md, "Who may connect").
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass
from typing import Any, Sequence
from urllib.parse import urlsplit

import numpy as np
import zmq

from .keys import CurveKeys, silence_hint
from .proto import SCHEMA_VERSION, wire


class PalpsimError(Exception):
    """Base of every error this package raises about talking to a server."""


class ServerError(PalpsimError):
    """The server refused a request; `code` is the ErrorCode number, `code_name` its name."""

    def __init__(self, request: str, code: int, message: str):
        self.request, self.code, self.message = request, code, message
        self.code_name = wire.ErrorCode.Name(code) if code in wire.ErrorCode.values() else str(code)
        super().__init__(f"{request} refused by the server: {self.code_name}: {message}")


class ServerTimeout(PalpsimError):
    """The server did not answer in time (not running, wrong address, or stuck)."""


@dataclass(frozen=True)
class PoseReply:
    """The server's answer to one pose (mm, N, s)."""

    seq: int
    force_n: np.ndarray        # force on the device, f = k (x - p), clamped
    proxy_mm: np.ndarray       # proxy p
    skin_point_mm: np.ndarray  # skin point X (the tip when out of contact)
    contact: bool              # the tip is inside the body
    depth_mm: float            # depth of the tip under the skin (0 outside)
    server_time_s: float       # server clock when the reply was made
    service_time_us: float     # server receive-to-send time
    rtt_s: float               # client-measured round trip of this pose


def _vec(v: Sequence[float]) -> "wire.Vec3":
    return wire.Vec3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _arr(v: Any) -> np.ndarray:
    return np.array((v.x, v.y, v.z), dtype=float)


# WatchSession's brick settings by the names the Python API and palpsim-view use
BRICK_ENCODINGS = {"int16": wire.BRICK_INT16, "float32": wire.BRICK_FLOAT32}
BRICK_COMPRESSIONS = {"none": wire.COMPRESSION_NONE, "zstd": wire.COMPRESSION_ZSTD}

# ViewSettings fields a view dict may set (server/render/view.h has their ranges; the
# server checks them and answers ERROR_BAD_VIEW with the range, so nothing is checked here)
VIEW_FIELDS = ("width", "height", "preset", "azimuth_deg", "elevation_deg", "zoom",
               "look_at_tip", "center_mm", "jpeg_quality", "show_tip", "show_proxy",
               "slice_fov_mm")


def _choice(name: str, value: Any, choices: dict[str, int]) -> int:
    """The enum number of `value` (a name of `choices`, or one of its numbers)."""
    if isinstance(value, str) and value in choices:
        return choices[value]
    if isinstance(value, int) and not isinstance(value, bool) and value in choices.values():
        return value
    raise ValueError(f"{name} = {value!r}: expected one of {', '.join(choices)}")


def view_settings(view: dict[str, Any]) -> "wire.ViewSettings":
    """A ViewSettings message holding exactly the fields of `view` (a dict keyed by
    VIEW_FIELDS); the fields it leaves out stay unset, so the server keeps their values."""
    unknown = sorted(set(view) - set(VIEW_FIELDS))
    if unknown:
        raise ValueError(f"view: unknown field(s) {', '.join(unknown)}; "
                         f"ViewSettings has {', '.join(VIEW_FIELDS)}")
    msg = wire.ViewSettings()
    for name, value in view.items():
        if value is None:
            continue
        try:
            if name == "center_mm":
                if len(value) != 3:
                    raise ValueError(f"{len(value)} values, expected 3 (x, y, z)")
                msg.center_mm.CopyFrom(_vec(value))
            elif name == "preset":
                msg.preset = str(value)
            elif name in ("look_at_tip", "show_tip", "show_proxy"):
                setattr(msg, name, bool(value))
            elif name in ("width", "height", "jpeg_quality"):
                setattr(msg, name, int(value))
            else:
                setattr(msg, name, float(value))
        except (TypeError, ValueError) as e:
            raise ValueError(f"view.{name} = {value!r}: {e}") from None
    return msg


def _check(request: str, reply: Any) -> None:
    """Raises ServerError when a reply carries an error."""
    if reply.HasField("error") and reply.error.code != wire.ERROR_NONE:
        raise ServerError(request, reply.error.code, reply.error.message)


def resolve_endpoint(endpoint: str, control_address: str | None) -> str:
    """`endpoint` with a wildcard host (`*`, 0.0.0.0, ::) replaced by the host of the
    control address, so a client can connect where the server bound all interfaces (its
    pose and stream endpoints are then tcp://0.0.0.0:PORT, as in a container)."""
    if not control_address or not endpoint.startswith("tcp://"):
        return endpoint
    host, _, port = endpoint[len("tcp://"):].rpartition(":")
    if host not in ("*", "0.0.0.0", "[::]", "::"):
        return endpoint
    control_host = urlsplit(control_address).hostname
    if not control_host or control_host in ("*", "0.0.0.0", "::"):
        control_host = "127.0.0.1"
    if ":" in control_host:
        control_host = f"[{control_host}]"
    return f"tcp://{control_host}:{port}"


class Client:
    """A connection to one palpsim-server's control path."""

    def __init__(self, address: str, timeout_s: float = 5.0, name: str = "palpsim-python",
                 context: zmq.Context | None = None, curve: CurveKeys | None = None,
                 client_token: str | bytes = b""):
        self.address = address
        self.timeout_s = timeout_s
        self.name = name
        self.curve = curve
        self.client_token = client_token.encode() if isinstance(client_token, str) else bytes(client_token)
        self._ctx = context or zmq.Context.instance()
        self._sock = self.socket(zmq.DEALER)
        # a DEALER without a peer (the server away, or its CURVE handshake refused and the
        # pipe torn down) blocks in send: bound it by the timeout as the reply is
        self._sock.setsockopt(zmq.SNDTIMEO, max(1, int(timeout_s * 1000)))
        self._sock.connect(address)
        self._ids = itertools.count(1)
        self._sessions: list[Session] = []

    def socket(self, kind: int) -> zmq.Socket:
        """A socket of this client's context (linger 0), a CURVE client when `curve` is set."""
        sock = self._ctx.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        if self.curve is not None:
            self.curve.apply(sock)
        return sock

    def silence(self, what: str) -> str:
        """A sentence for a server that did not answer `what` in time."""
        return (f"no reply to {what} from {self.address} within {self.timeout_s:g} s (is "
                f"palpsim-server running there?){silence_hint(self.curve)}")

    # -- control requests -------------------------------------------------------------

    def _request(self, field: str, body: Any) -> Any:
        """Sends one ControlRequest with `body` in `field` and returns the reply's body."""
        rid = next(self._ids)
        req = wire.ControlRequest(schema_version=SCHEMA_VERSION, request_id=rid,
                                  client_token=self.client_token)
        getattr(req, field).CopyFrom(body)
        try:
            self._sock.send(req.SerializeToString())
        except zmq.Again:
            raise ServerTimeout(self.silence(field)) from None
        deadline = time.monotonic() + self.timeout_s
        while True:
            left_ms = int(max(0.0, deadline - time.monotonic()) * 1000)
            if not self._sock.poll(left_ms, zmq.POLLIN):
                raise ServerTimeout(self.silence(field))
            reply = wire.ControlReply()
            try:
                reply.ParseFromString(self._sock.recv())
            except Exception as e:  # protobuf raises DecodeError, a plain Exception subclass
                raise PalpsimError(f"{field}: the server's reply does not parse: {e}") from None
            # a late answer to an earlier request that timed out: skip it
            if reply.request_id != rid and reply.request_id != 0:
                continue
            _check(f"ControlRequest.{field}", reply)
            if reply.WhichOneof("body") != field:
                raise PalpsimError(f"{field}: the server answered with "
                                   f"{reply.WhichOneof('body')!r} instead")
            return getattr(reply, field)

    def info(self) -> "wire.ServerInfo":
        """The server's description: scene, patient grid and bounds, endpoints, limits."""
        return self._request("info", wire.InfoRequest())

    def stats(self) -> "wire.StatsReply":
        """Server counters, pose service times, every stage's StageInfo (built, bytes held,
        mean time) and the deformation backend and counters (`.server.deform_*`)."""
        return self._request("stats", wire.StatsRequest())

    def load_scene(self, path: str | None = None, text: str | None = None) -> "wire.ServerInfo":
        """Asks the server to serve another scene (a file it can read, or scene text).

        The server prepares the patient on a thread of its own and answers when it is
        served, so a CT that is not in its cache may need a `timeout_s` of minutes; other
        clients are answered meanwhile. While another load runs it raises ServerError
        with code_name ERROR_LOAD_RUNNING (`info().scene_loading` names that load)."""
        if (path is None) == (text is None):
            raise ValueError("load_scene: give exactly one of path or text")
        body = wire.LoadScene(path=path) if path is not None else wire.LoadScene(text=text)
        return self._request("load_scene", body).server

    def watch(self, session_id: int = 0, frames: bool = True, bricks: bool = False,
              view: "dict[str, Any] | wire.ViewSettings | None" = None, hold_s: float | None = None,
              brick_encoding: str = "int16", compression: str = "none") -> "wire.WatchReply":
        """Watches a session on the server's stream endpoint (PROTOCOL.md, "Frames and
        bricks") and returns the WatchReply: the session watched (the newest open one when
        `session_id` is 0), `stream_endpoint` (connect a SUB there), `frame_topic` and
        `brick_topic` to subscribe to, and the session's whole effective view.

        `view` changes the session's view: a dict of ViewSettings fields (`width`, `height`
        in pixels, `preset`, `azimuth_deg`, `elevation_deg`, `zoom`, `look_at_tip`,
        `center_mm` as (x, y, z) mm, `jpeg_quality`, `show_tip`, `show_proxy`,
        `slice_fov_mm`) or a ViewSettings message; fields left out keep their current value.
        `hold_s` keeps the session rendered (frames) or published (bricks) for that long
        from now without a subscriber (0 ends an earlier hold; None leaves any hold as it is).
        `brick_encoding` is "int16" (HU) or "float32"; `compression` "none" or "zstd".
        Refusals raise ServerError (ERROR_UNKNOWN_SESSION, ERROR_NOT_OWNER, ERROR_NO_SESSION_OPEN,
        ERROR_NOT_BUILT, ERROR_BAD_VIEW, ERROR_BAD_PARAMETER) with the server's sentence."""
        body = wire.WatchSession(session_id=int(session_id), frames=bool(frames),
                                 bricks=bool(bricks),
                                 brick_encoding=_choice("brick_encoding", brick_encoding,
                                                        BRICK_ENCODINGS),
                                 brick_compression=_choice("compression", compression,
                                                           BRICK_COMPRESSIONS))
        if hold_s is not None:
            body.hold_s = float(hold_s)
        if view is not None:
            body.view.CopyFrom(view if isinstance(view, wire.ViewSettings) else view_settings(view))
        return self._request("watch", body)

    def pick(self, session_id: int, x_px: float, y_px: float) -> "wire.PickReply":
        """The skin point under pixel (x_px, y_px) of a session's frame (x from the left
        edge, y from the top, pixel centres at .5): the server casts that pixel's ray with
        the session's current view and answers with its first point in the body
        (`.hit`, `.point_mm`), the ray (`.ray_origin_mm`, unit `.ray_direction`) and the view
        it used. A pixel outside the frame's 3D view raises ServerError
        (ERROR_BAD_PARAMETER); a session that is not this client's, ERROR_NOT_OWNER."""
        return self._request("pick", wire.PickRequest(session_id=int(session_id), x_px=float(x_px),
                                                      y_px=float(y_px)))

    def open_session(self, client_name: str | None = None) -> "Session":
        """Opens a session with its own proxy state and the scene's haptics parameters."""
        reply = self._request("open", wire.OpenSession(client_name=client_name or self.name))
        session = Session(self, reply)
        self._sessions.append(session)
        return session

    def close(self) -> None:
        """Closes this client's open sessions (best effort) and its sockets."""
        for s in list(self._sessions):
            try:
                s.close()
            except PalpsimError:
                s._close_socket()
        self._sock.close(0)

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class Session:
    """One open session: its own proxy state on the server and its own pose socket."""

    def __init__(self, client: Client, reply: "wire.OpenReply"):
        self.client = client
        self.id: int = reply.session_id
        self.pose_endpoint: str = resolve_endpoint(reply.pose_endpoint, client.address)
        self.params: "wire.HapticsParams" = reply.params
        self.server_info: "wire.ServerInfo" = reply.server
        self._sock = client.socket(zmq.DEALER)
        self._sock.setsockopt(zmq.SNDTIMEO, max(1, int(client.timeout_s * 1000)))  # as the control socket's
        self._sock.connect(self.pose_endpoint)
        self._seq = 0
        self._sent: dict[int, float] = {}  # seq -> perf_counter at send, for round trips
        self.closed = False

    # -- pose path --------------------------------------------------------------------

    def send_pose(self, tip_mm: Sequence[float], client_time_s: float = 0.0,
                  seq: int | None = None, reset_proxy: bool = False) -> int:
        """Sends one pose without waiting (replies come back in order); returns its seq.

        `client_time_s` is the device's clock; when it grows from pose to pose the server
        uses it for the force-rate clamp, so simulated times give reproducible forces.
        `reset_proxy` resets the proxy state right before this pose."""
        if seq is None:
            self._seq += 1
            seq = self._seq
        req = wire.PoseRequest(schema_version=SCHEMA_VERSION, session_id=self.id, seq=seq,
                               tip_mm=_vec(tip_mm), client_time_s=client_time_s,
                               reset_proxy=reset_proxy)
        self._sent[seq] = time.perf_counter()
        try:
            self._sock.send(req.SerializeToString())
        except zmq.Again:
            self._sent.pop(seq, None)
            raise ServerTimeout(f"pose {seq} could not be sent to {self.pose_endpoint} within "
                                f"{self.client.timeout_s:g} s{silence_hint(self.client.curve)}") from None
        return seq

    def recv_reply(self, timeout_s: float | None = None) -> PoseReply:
        """Receives the next pose reply; raises ServerError if that pose was refused."""
        timeout_s = self.client.timeout_s if timeout_s is None else timeout_s
        if not self._sock.poll(int(timeout_s * 1000), zmq.POLLIN):
            raise ServerTimeout(f"no pose reply from {self.pose_endpoint} within {timeout_s:g} s"
                                f"{silence_hint(self.client.curve)}")
        data = self._sock.recv()
        now = time.perf_counter()
        r = wire.PoseReply()
        try:
            r.ParseFromString(data)
        except Exception as e:
            raise PalpsimError(f"a pose reply does not parse: {e}") from None
        sent = self._sent.pop(r.seq, None)
        _check(f"PoseRequest seq {r.seq}", r)
        return PoseReply(seq=r.seq, force_n=_arr(r.force_n), proxy_mm=_arr(r.proxy_mm),
                         skin_point_mm=_arr(r.skin_point_mm), contact=r.contact,
                         depth_mm=r.depth_mm, server_time_s=r.server_time_s,
                         service_time_us=r.service_time_us,
                         rtt_s=(now - sent) if sent is not None else float("nan"))

    def pose(self, tip_mm: Sequence[float], client_time_s: float = 0.0,
             seq: int | None = None, reset_proxy: bool = False) -> PoseReply:
        """Sends one pose and waits for its reply."""
        seq = self.send_pose(tip_mm, client_time_s, seq=seq, reset_proxy=reset_proxy)
        reply = self.recv_reply()
        if reply.seq != seq:
            raise PalpsimError(f"pose reply out of order: sent seq {seq}, got {reply.seq}")
        return reply

    # -- control path -----------------------------------------------------------------

    def reset(self) -> None:
        """Resets the proxy state as if freshly opened (parameters are kept)."""
        self.client._request("reset", wire.ResetSession(session_id=self.id))

    def set_parameter(self, name: str, value: float) -> "wire.HapticsParams":
        """Sets one haptics parameter (names and ranges of scene.proto's Haptics)."""
        reply = self.client._request("set_parameter",
                                     wire.SetParameter(session_id=self.id, name=name, value=value))
        self.params = reply.params
        return reply.params

    def stats(self) -> "wire.SessionStats":
        """This session's counters and parameters, its stages, and its deformation
        (`.deform`, a DeformSessionStats: steps, dropped contacts, stage times in ms,
        moved elements, sweeps, converged, inversion residual, backend; unset when the
        scene asks for no deformation: check `.HasField("deform")`). With the elastic
        model, `.deform.elastic` (ElasticForceStats) holds the latest step's force on the
        fingertip and its stiffness, and the jumps the haptic thread saw rendering them."""
        return self.client._request("stats", wire.StatsRequest(session_id=self.id)).session

    def close(self) -> int:
        """Closes the session; returns how many poses it answered."""
        if self.closed:
            return 0
        try:
            reply = self.client._request("close", wire.CloseSession(session_id=self.id))
        finally:
            self._close_socket()
        return reply.poses

    def _close_socket(self) -> None:
        self.closed = True
        self._sock.close(0)
        if self in self.client._sessions:
            self.client._sessions.remove(self)

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc: Any) -> None:
        if not self.closed:
            try:
                self.close()
            except PalpsimError:
                self._close_socket()
