"""LocalServer's process handling, with small shell scripts in place of palpsim-server
(the real server is exercised in test_end_to_end.py)."""

from __future__ import annotations

import os

import pytest

from palpsim.server import LocalServer, ServerStartError


def _script(tmp_path, body: str):
    p = tmp_path / "fake-server"
    p.write_text("#!/bin/sh\n" + body + "\n")
    os.chmod(p, 0o755)
    return p


def test_ready_line_gives_the_address_and_stop_ends_the_process(tmp_path):
    p = _script(tmp_path, 'echo "loading"; echo "palpsim-server: ready on tcp://127.0.0.1:5999 '
                          'poses tcp://127.0.0.1:6000"; exec sleep 30')
    srv = LocalServer(p, scene="s.textproto", log_path=tmp_path / "log.txt")
    assert srv.command()[1:] == ["--bind", "tcp://127.0.0.1:*", "--scene", "s.textproto"]
    assert srv.start() == "tcp://127.0.0.1:5999"
    assert srv.proc.poll() is None
    srv.stop(timeout_s=5)
    assert srv.proc.poll() is not None
    assert "loading" in (tmp_path / "log.txt").read_text()


def test_early_exit_quotes_the_servers_output(tmp_path):
    p = _script(tmp_path, 'echo "error: scene.textproto: haptics.friction: out of range" >&2; exit 3')
    with pytest.raises(ServerStartError) as e:
        LocalServer(p).start()
    assert "exited with status 3" in str(e.value)
    assert "haptics.friction: out of range" in str(e.value)


def test_no_ready_line_times_out_and_the_process_is_stopped(tmp_path):
    p = _script(tmp_path, 'echo "preparing"; exec sleep 30')
    srv = LocalServer(p, startup_timeout_s=0.5)
    with pytest.raises(ServerStartError, match="did not say 'ready on ADDR' within 0.5 s"):
        srv.start()
    assert srv.proc.poll() is not None
