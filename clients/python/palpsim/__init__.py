"""palpsim: client library, batch palpation runner and demo for palpsim-server.

Modules: `client` (sessions, poses, control requests), `plan` (plan files and their
expansion into presses), `runner` (a plan's presses over parallel sessions), `batch`
(palpsim-batch), `study` (plans x patients x a grid), `results` (tidy table and summary),
`plots` (PNG figures), `server` (start and stop a local palpsim-server), `demo`
(palpsim-demo, the lumbar spine palpation).
"""

import os as _os

__version__ = "0.1.0"

# the protobuf modules protoc generates into _proto/palpsim/ import each other as
# `from palpsim import scene_pb2`: adding that folder to this package's path makes
# them submodules of this package (palpsim.wire_pb2), whatever sys.path holds
__path__.append(_os.path.join(_os.path.dirname(__file__), "_proto", "palpsim"))

# the main entry points, imported on first use (the client needs the generated protobuf
# modules; plans, tables and plots do not)
_LAZY = {"Client": "client", "Session": "client", "ServerError": "client",
         "ServerTimeout": "client", "PalpsimError": "client", "load_plan": "plan",
         "parse_plan": "plan", "PlanError": "plan", "run_plan": "runner", "LocalServer": "server"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib
        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'palpsim' has no attribute {name!r}")
