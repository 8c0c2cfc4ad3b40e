"""``acinoset resident status|stop``: the residents of this user, and stopping them."""

from __future__ import annotations

import json
import os
import signal
import time
from collections import namedtuple

from graph.app.resident.client import forward_signal, wanted
from graph.app.resident.protocol import DEFAULT_IDLE_S, IDLE, SWITCH, key_of, lock_held, runtime_dir


class Resident(namedtuple("Resident", "key pid ready served started last idle_s python current")):
    """A running resident, as its lock file describes it: ``key``, ``pid`` (int or None), ``ready``,
    ``served`` (solves), ``started`` and ``last`` (times or None), ``idle_s``, ``python`` and
    ``current`` (its key is this install's, Python's and environment's)."""

    __slots__ = ()


def residents(env: dict[str, str] | None = None) -> list[Resident]:
    """This user's running residents (their lock held), newest first."""
    env = dict(os.environ) if env is None else env
    d = runtime_dir(env)
    try:
        mine = key_of(env)
    except OSError:
        mine = ""
    out = []
    for lock in d.glob("*.lock"):
        if not lock_held(lock):
            continue
        try:
            info = json.loads(lock.read_text(encoding="utf-8") or "{}")
        except (OSError, ValueError):
            info = {}
        out.append(Resident(key=lock.stem, pid=info.get("pid"), ready=bool(info.get("ready")),
                            served=int(info.get("served") or 0), started=info.get("started"), last=info.get("last"),
                            idle_s=info.get("idle_s"), python=info.get("python"), current=lock.stem == mine))
    return sorted(out, key=lambda r: -(r.started or 0.0))


def stop(env: dict[str, str] | None = None, wait_s: float = 30.0) -> list[Resident]:
    """Ask every running resident to stop (SIGTERM: solves being served finish first) and wait up
    to ``wait_s`` for them to exit; return those asked."""
    env = dict(os.environ) if env is None else env
    asked = [r for r in residents(env) if r.pid]
    for r in asked:
        forward_signal(r.pid, signal.SIGTERM)
    d = runtime_dir(env)
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline and any(lock_held(d / f"{r.key}.lock") for r in asked):
        time.sleep(0.05)
    return asked


def register(sub) -> None:
    """``acinoset resident status|stop``."""
    p = sub.add_parser("resident", description="The warm background process that serves 'acinoset solve': "
                       "started by a solve, it exits after " + f"{DEFAULT_IDLE_S / 60:g} minutes without one "
                       f"(${IDLE} seconds). {SWITCH}=0 turns it off.")
    rs = p.add_subparsers(dest="resident_command", required=True, metavar="{status,stop}")
    rs.add_parser("status", help="list this user's resident processes").set_defaults(func=run_status)
    rs.add_parser("stop", help="stop them (a solve being served finishes first)").set_defaults(func=run_stop)


def run_status(args) -> int:
    found = residents()
    if not found:
        off = not wanted(["solve"], dict(os.environ))
        print(f"no resident process ({f'off: {SWITCH}=0' if off else 'the next acinoset solve starts one'})")
        return 0
    now = time.time()
    for r in found:
        state = "ready" if r.ready else "warming up"
        up = f"up {now - r.started:.0f} s" if r.started else "starting"
        last = f", last solve {now - r.last:.0f} s ago" if r.last else ""
        which = "this install" if r.current else "another install, Python or environment"
        idle = f"{r.idle_s:g} s" if r.idle_s else "?"
        print(f"pid {r.pid}: {state}, {up}, served {r.served}{last}; idle exit after {idle}; key {r.key} ({which})")
    return 0


def run_stop(args) -> int:
    asked = stop()
    if not asked:
        print("no resident process")
    for r in asked:
        print(f"stopped pid {r.pid} (key {r.key})")
    return 0
