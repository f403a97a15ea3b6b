"""Keys and identity through the Python client (docs/security.md): key files as
palpsim-keys writes them, and the real palpsim-server (from $PALPSIM_BUILD_DIR) with CURVE:
an allowed key opens a session and feels forces, its StreamClient gets the session's
bricks, an unknown key and a client without keys time out with a sentence that says why,
and another key's requests for the session are refused (ERROR_NOT_OWNER). Key files of the
wrong half and client pairs that do not match are refused, naming the file."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from palpsim.client import Client, ServerError, ServerTimeout
from palpsim.keys import CurveKeys, KeyFileError, read_key_file, read_secret_key_file
from palpsim.proto import wire
from palpsim.server import LocalServer
from palpsim.stream import StreamClient

ROOT = Path(__file__).resolve().parents[3]

# bricks need no OpenGL: the cheapest scene with a stream
SCENE = """
name: "phantom 4 mm, bricks (python security test)"
phantom { voxel_mm: 4.0 }
effects { haptics: true bricks: true }
"""
# An admitted client's first reply comes within ~100 ms on loopback (handshake included);
# a refused one never comes, so 1.5 s of silence is a refusal.
SILENCE_S = 1.5
# a healthy server answers within milliseconds; 10 s covers a loaded 2-core machine
REPLY_S = 10.0


def _exe(name: str) -> Path:
    d = os.environ.get("PALPSIM_BUILD_DIR")
    p = Path(d) / name if d else ROOT / "build" / name
    if not (p.is_file() and os.access(p, os.X_OK)):
        reason = f"SKIPPED: no {name} in $PALPSIM_BUILD_DIR={os.environ.get('PALPSIM_BUILD_DIR')}"
        print(reason)
        pytest.skip(reason)
    return p


def _keys(tmp: Path, *names: str) -> None:
    for n in names:
        subprocess.run([str(_exe("palpsim-keys")), n, "--dir", str(tmp)], check=True,
                       capture_output=True)


def test_key_files(tmp_path):
    _keys(tmp_path, "alice")
    pub = read_key_file(tmp_path / "alice.key")
    assert len(pub) == 40
    assert CurveKeys.from_files(tmp_path / "alice.key", tmp_path / "alice.key_secret").client_public == pub
    # a bad line is named with its file and line
    bad = tmp_path / "bad.key"
    bad.write_text("# a comment\nshort\n")
    with pytest.raises(KeyFileError, match=r"bad\.key:2: not a key: 5 characters"):
        read_key_file(bad)
    two = tmp_path / "two.key"
    two.write_text((tmp_path / "alice.key").read_text() * 2)
    with pytest.raises(KeyFileError, match="a second key on line 4"):
        read_key_file(two)


def test_keys_of_the_wrong_half_and_pairs_that_do_not_match_are_refused(tmp_path):
    _keys(tmp_path, "server", "alice", "other")
    # the server's secret key as --server-key, a public key as --client-key: named and refused
    with pytest.raises(KeyFileError, match=r"server\.key_secret: a secret key \(palpsim-keys marked it so"):
        CurveKeys.from_files(tmp_path / "server.key_secret", tmp_path / "alice.key_secret")
    with pytest.raises(KeyFileError, match=r"alice\.key: a public key \(palpsim-keys marked it so"):
        CurveKeys.from_files(tmp_path / "server.key", tmp_path / "alice.key")
    # without the comment the name tells; a name that tells nothing is taken as asked
    bare = tmp_path / "bare.key"
    bare.write_text(read_key_file(tmp_path / "alice.key").decode() + "\n")
    with pytest.raises(KeyFileError, match=r"bare\.key: a public key \(its name ends in \.key\)"):
        read_key_file(bare, half="secret")
    mounted = tmp_path / "mounted"
    mounted.write_text(read_key_file(tmp_path / "alice.key_secret").decode() + "\n")
    assert read_secret_key_file(mounted)[1] == read_key_file(tmp_path / "alice.key")
    # alice.key beside alice.key_secret replaced by another key: not a pair
    (tmp_path / "alice.key").write_text((tmp_path / "other.key").read_text())
    with pytest.raises(KeyFileError, match=r"alice\.key_secret and .*alice\.key are not a pair"):
        CurveKeys.from_files(tmp_path / "server.key", tmp_path / "alice.key_secret")
    with pytest.raises(KeyFileError, match="are not a pair"):
        read_secret_key_file(mounted, public_path=tmp_path / "other.key")


@pytest.fixture(scope="module")
def curve_server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("curve")
    _keys(tmp, "server", "alice", "bob", "mallory")
    (tmp / "allowed").write_text((tmp / "alice.key").read_text() + (tmp / "bob.key").read_text())
    scene = tmp / "scene.textproto"
    scene.write_text(SCENE)
    with LocalServer(_exe("palpsim-server"), scene=scene, startup_timeout_s=120,
                     log_path=tmp / "server.log",
                     extra_args=["--curve-secret", str(tmp / "server.key_secret"),
                                 "--allow", str(tmp / "allowed")]) as srv:
        yield srv, tmp


def _curve(tmp: Path, who: str, server: str = "server") -> CurveKeys:
    return CurveKeys.from_files(tmp / f"{server}.key", tmp / f"{who}.key_secret")


def test_allowed_key_is_served_and_owns_its_session(curve_server):
    srv, tmp = curve_server
    with Client(srv.address, timeout_s=REPLY_S, curve=_curve(tmp, "alice")) as a, \
            a.open_session("alice") as s:
        assert s.server_info.curve
        hi, lo = s.server_info.patient.body_max_mm, s.server_info.patient.body_min_mm
        x, z = 0.5 * (lo.x + hi.x), 0.5 * (lo.z + hi.z)
        forces = [np.linalg.norm(s.pose((x, hi.y + 5 - k, z)).force_n) for k in range(41)]
        assert max(forces) > 0
        # the stream speaks CURVE too: alice gets her session's key bricks
        reply = a.watch(session_id=s.id, frames=False, bricks=True)
        with StreamClient.from_watch(reply, srv.address, curve=a.curve) as sc:
            u = sc.receive(REPLY_S)
            assert u is not None and u.bricks
        # bob is allowed, but the session is alice's
        with Client(srv.address, timeout_s=REPLY_S, curve=_curve(tmp, "bob")) as b:
            for request, body in (("close", wire.CloseSession(session_id=s.id)),
                                  ("reset", wire.ResetSession(session_id=s.id)),
                                  ("stats", wire.StatsRequest(session_id=s.id))):
                with pytest.raises(ServerError) as e:
                    b._request(request, body)
                assert e.value.code == wire.ERROR_NOT_OWNER, request
            with pytest.raises(ServerError, match="ERROR_NOT_OWNER"):
                b.watch(session_id=s.id, frames=False, bricks=True)
        assert s.stats().poses == 41


def test_refused_clients_time_out_with_a_reason(curve_server):
    srv, tmp = curve_server
    with Client(srv.address, timeout_s=SILENCE_S, curve=_curve(tmp, "mallory")) as m:
        with pytest.raises(ServerTimeout, match="allow-list"):
            m.info()
    with Client(srv.address, timeout_s=SILENCE_S, curve=_curve(tmp, "alice", server="bob")) as w:
        with pytest.raises(ServerTimeout, match="not its public key"):
            w.info()
    with Client(srv.address, timeout_s=SILENCE_S) as p:
        with pytest.raises(ServerTimeout, match="give --server-key and --client-key"):
            p.info()
    with Client(srv.address, timeout_s=REPLY_S, curve=_curve(tmp, "alice")) as a:
        assert a.stats().server.curve_refused >= 1  # mallory's key reached the ZAP handler
