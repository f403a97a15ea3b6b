"""Runs a palpation plan's presses over N parallel sessions of a palpsim-server and returns
the canonical tidy table of every pose (run_plan); palpsim-batch (batch) and studies
(study) both run plans through it.

Determinism: every press starts with a proxy reset ordered with its first pose, its
poses are a function of the plan and of the replies' contact flags, its pose times
(client_time_s, which the server's force-rate clamp uses) are trajectory times, and its
sequence numbers are a function of its place in the plan. Which session runs which press
changes nothing but the timing columns, and the table is sorted before it is written.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import pandas as pd

from .client import Client, PalpsimError
from .keys import CurveKeys
from .plan import Plan, PressPath, PressTask, expand
from .results import finish_table

# pose sequence numbers: (press index << SEQ_SHIFT) + step + 1, unique over the plan
SEQ_SHIFT = 24
# client_time_s = CLOCK_OFFSET_S + t_s: the server uses the growth of client_time_s for the
# force-rate clamp only while it is positive (PROTOCOL.md), and t_s starts at 0
CLOCK_OFFSET_S = 1.0


@dataclass
class RunResult:
    """A finished run: the canonical tidy table and how the run went."""

    table: pd.DataFrame
    wall_s: float
    sessions: int
    server: dict


def run_press(session, plan: Plan, task: PressTask, worker: int) -> dict[str, np.ndarray]:
    """Runs one press on an open session; returns its rows as columns."""
    path = PressPath(plan, task.point)
    d = path.direction
    rows: list[tuple] = []
    base = task.index << SEQ_SHIFT
    while not path.done:
        k, t_s, phase, s, tip = path.pose()
        if k + 1 >= 1 << SEQ_SHIFT:
            raise PalpsimError(f"press {task.index} exceeded {1 << SEQ_SHIFT} poses")
        r = session.pose(tip, client_time_s=CLOCK_OFFSET_S + t_s, seq=base + k + 1,
                         reset_proxy=(k == 0))
        f = r.force_n
        rows.append((k, phase, t_s, s, tip[0], tip[1], tip[2], r.depth_mm, r.contact,
                     f[0], f[1], f[2], float(np.sqrt(f @ f)), -float(f @ d),
                     r.proxy_mm[0], r.proxy_mm[1], r.proxy_mm[2],
                     r.skin_point_mm[0], r.skin_point_mm[1], r.skin_point_mm[2],
                     r.seq, r.rtt_s * 1e6, r.service_time_us))
        path.advance(r.contact)
    names = ("step", "phase", "t_s", "travel_mm", "tip_x_mm", "tip_y_mm", "tip_z_mm",
             "depth_mm", "contact", "force_x_n", "force_y_n", "force_z_n", "force_n",
             "press_force_n", "proxy_x_mm", "proxy_y_mm", "proxy_z_mm", "skin_x_mm",
             "skin_y_mm", "skin_z_mm", "seq", "rtt_us", "service_us")
    cols = {n: np.array(c) for n, c in zip(names, zip(*rows))}
    n = len(rows)
    p = task.point
    cols.update(point_id=np.full(n, p.point_id), iu=np.full(n, p.iu), iv=np.full(n, p.iv),
                u_mm=np.full(n, p.u_mm), v_mm=np.full(n, p.v_mm), rep=np.full(n, task.rep),
                session=np.full(n, worker))
    return cols


def run_plan(plan: Plan, address: str, sessions: int = 1, timeout_s: float = 10.0,
             progress: bool = True,
             on_press: Callable[[PressTask], None] | None = None,
             curve: CurveKeys | None = None) -> RunResult:
    """Runs every press of the plan over `sessions` parallel sessions (one thread and one
    connection each, CURVE with `curve`) and returns the canonical table. Raises the first
    error a session met (ServerError, ServerTimeout) after stopping the others."""
    if sessions < 1:
        raise ValueError(f"sessions must be at least 1, got {sessions}")
    tasks = expand(plan)
    todo: queue.Queue[PressTask] = queue.Queue()
    for t in tasks:
        todo.put(t)
    results: dict[int, dict[str, np.ndarray]] = {}
    errors: list[BaseException] = []
    stop = threading.Event()
    lock = threading.Lock()
    # every session is open before any press starts, so that all of them share the work
    ready = threading.Barrier(sessions)
    server: dict = {}

    from tqdm import tqdm
    bar = tqdm(total=len(tasks), unit="press", disable=not progress, dynamic_ncols=True,
               desc=plan.name[:30])

    def worker(w: int) -> None:
        try:
            with Client(address, timeout_s=timeout_s, name=f"palpsim-batch/{w}",
                        curve=curve) as client:
                session = client.open_session()
                if w == 0:
                    info = session.server_info
                    server.update(scene=info.scene_name, scene_file=info.scene_file,
                                  patient=info.patient.source,
                                  generation=int(info.scene_generation))
                for name, value in plan.parameters.items():
                    session.set_parameter(name, value)
                ready.wait(timeout=max(timeout_s, 1.0) * 3)
                while not stop.is_set():
                    try:
                        task = todo.get_nowait()
                    except queue.Empty:
                        break
                    cols = run_press(session, plan, task, w)
                    with lock:
                        results[task.index] = cols
                        bar.update(1)
                    if on_press:
                        on_press(task)
                session.close()
        except threading.BrokenBarrierError:
            stop.set()  # another session failed to open; its error is the one reported
        except BaseException as e:  # noqa: BLE001 - handed to the caller below
            with lock:
                errors.append(e)
            stop.set()
            ready.abort()

    t0 = time.perf_counter()
    threads = [threading.Thread(target=worker, args=(w,), daemon=True) for w in range(sessions)]
    for th in threads:
        th.start()
    try:
        for th in threads:
            while th.is_alive():
                th.join(0.2)
    except KeyboardInterrupt:
        stop.set()
        raise
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    if errors:
        raise errors[0]
    if stop.is_set() and len(results) != len(tasks):
        raise PalpsimError("the sessions could not all be opened in time")
    if len(results) != len(tasks):
        raise PalpsimError(f"only {len(results)} of {len(tasks)} presses finished")
    frames = [pd.DataFrame(results[i]) for i in range(len(tasks))]
    table = finish_table(pd.concat(frames, ignore_index=True))
    return RunResult(table=table, wall_s=wall, sessions=sessions, server=server)
