"""palpsim-batch's command line: clear errors and exit codes before and without a server."""

from __future__ import annotations

import json
import socket

from conftest import PLAN
from palpsim.batch import main


def _plan_file(tmp_path, data=PLAN):
    p = tmp_path / "plan.json"
    p.write_text(json.dumps(data))
    return p


def _unused_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_bad_plan_exits_2_naming_the_field(tmp_path, capsys):
    data = json.loads(json.dumps(PLAN))
    data["press"]["speed_mm_per_s"] = -3
    rc = main([str(_plan_file(tmp_path, data)), "--connect", "tcp://127.0.0.1:1"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "plan.json: press.speed_mm_per_s: must be in" in err


def test_bad_table_extension_exits_2(tmp_path, capsys):
    rc = main([str(_plan_file(tmp_path)), "--connect", "tcp://127.0.0.1:1", "--table", "x.xlsx"])
    assert rc == 2 and "--table" in capsys.readouterr().err


def test_no_server_is_a_clear_timeout(tmp_path, capsys):
    addr = f"tcp://127.0.0.1:{_unused_port()}"
    rc = main([str(_plan_file(tmp_path)), "--connect", addr, "--timeout", "0.3",
               "--no-progress", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 1
    assert f"no reply to open from {addr}" in err and "palpsim-server running" in err
    # nothing written for a run that did not happen
    assert not (tmp_path / "out" / "summary.json").exists()


def test_missing_server_binary_is_named(tmp_path, capsys):
    rc = main([str(_plan_file(tmp_path)), "--start-server", str(tmp_path / "no-server"),
               "--no-progress", "--out", str(tmp_path / "out")])
    assert rc == 1 and "no-server: no palpsim-server executable" in capsys.readouterr().err
