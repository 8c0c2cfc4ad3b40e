"""The ``acinoset`` command: the library's subcommands (:data:`graph.app.cli.COMMANDS`) and the service's,
``serve``, ``worker``, ``users`` and ``jobs``, which :func:`register` adds. ``python -m service``
runs the same command. Every flag left out falls back to the environment
(``ACINOSET_*``, see :mod:`service.settings`), then to the defaults.
"""

from __future__ import annotations

import argparse
import functools
import os
import re
import sys
from pathlib import Path

from graph.app.cli import COMMANDS as LIBRARY_COMMANDS
from graph.app.cli import Command
from graph.app.cli import main as cli_main

WORKER_TTL = 60  # seconds a dead worker's name stays registered in Redis (idle workers renew it)


class Refused(Exception):
    """A subcommand cannot do what it was asked; the message says why in one line."""


def _refusing(command: str):
    """Wrap a subcommand's function: a :class:`Refused` (or the job table's ``StoreRefused``) prints
    ``acinoset <command>: <why>`` on stderr and exits with status 2."""
    def wrap(fn):
        @functools.wraps(fn)
        def run(args: argparse.Namespace) -> int:
            from service.store import StoreRefused

            try:
                return fn(args)
            except (Refused, StoreRefused) as e:
                print(f"acinoset {command}: {e}", file=sys.stderr)
                return 2
        return run
    return wrap


def _settings(args: argparse.Namespace, *names: str):
    from service.settings import Settings

    overrides = {n: getattr(args, n) for n in names if getattr(args, n, None) is not None}
    return Settings(**overrides)


def _data_dir_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data-dir", help="where jobs, results and the job table live "
                                      "(default: $ACINOSET_DATA_DIR or ~/.local/share/acinoset)")


def register(subparsers) -> None:
    """Add ``serve``, ``worker``, ``users`` and ``jobs`` to an argparse subparsers object."""
    from service.store import STATUSES

    p = subparsers.add_parser("serve",
                              description="Run the REST job service for a lab: upload keypoints and a "
                                          "calibration, poll the job, download the 3D result.")
    p.add_argument("--host", help="address to listen on (default 127.0.0.1; 0.0.0.0 for the whole network)")
    p.add_argument("--port", type=int, help="port (default 8000)")
    _data_dir_arg(p)
    p.add_argument("--backend", choices=["embedded", "rq"],
                   help="embedded: solves run in this server's child processes (default); "
                        "rq: on 'acinoset worker' processes through Redis")
    p.add_argument("--redis-url", help="Redis for --backend rq (default redis://127.0.0.1:6379/0)")
    p.add_argument("--workers", type=int, help="embedded: solves at once (default: the number of cores)")
    p.add_argument("--log-level", choices=["debug", "info", "warning", "error"], help="default info")
    p.add_argument("--access-log", action="store_true", help="log every request")
    p.set_defaults(func=serve)

    w = subparsers.add_parser("worker",
                              description="Join the pool of an RQ-backed server: take jobs from Redis, solve "
                                          "them, hand the results back. Run it on any machine with acinoset "
                                          "installed that reaches the Redis server.")
    w.add_argument("--redis-url", help="the server's Redis (default redis://127.0.0.1:6379/0)")
    w.add_argument("--queue-name", help="default acinoset")
    w.add_argument("--name", help="worker name shown in jobs, unique among live workers (default: host.pid.random)")
    w.add_argument("--data-dir", help="the server's data dir as this machine mounts it, for a server that shares "
                                      "it with its workers (ACINOSET_SHARED_DATA_DIR): jobs' files are read and "
                                      "results written there instead of through Redis (default: $ACINOSET_DATA_DIR "
                                      "or ~/.local/share/acinoset)")
    w.add_argument("--burst", action="store_true", help="stop when the queue is empty")
    w.add_argument("--log-level", choices=["debug", "info", "warning", "error"], help="default info")
    w.set_defaults(func=worker)

    u = subparsers.add_parser("users",
                              description="Users of the job service. Tokens are printed once, on the last "
                                          "line, and stored only as a hash.")
    us = u.add_subparsers(dest="users_command", required=True, metavar="{add,list,token,remove}")
    a = us.add_parser("add", help="add a user and print its token (last line)")
    a.add_argument("name")
    a.add_argument("--admin", action="store_true", help="can see and cancel everyone's jobs")
    _data_dir_arg(a)
    a.set_defaults(func=users_add)
    ls = us.add_parser("list", help="list users and their job counts")
    _data_dir_arg(ls)
    ls.set_defaults(func=users_list)
    t = us.add_parser("token", help="revoke a user's tokens and print a new one (last line)")
    t.add_argument("name")
    t.add_argument("--enable", action="store_true", help="also let a removed user sign in again")
    _data_dir_arg(t)
    t.set_defaults(func=users_token)
    r = us.add_parser("remove", help="revoke a user's tokens and cancel its active jobs (jobs are kept)")
    r.add_argument("name")
    _data_dir_arg(r)
    r.set_defaults(func=users_remove)

    j = subparsers.add_parser("jobs",
                              description="The job table and result files of a data dir, for its admin. "
                                          "Safe while the server runs.")
    js = j.add_subparsers(dest="jobs_command", required=True, metavar="{list,prune}")
    jl = js.add_parser("list", help="jobs newest first, with their owner, status and disk use")
    jl.add_argument("--owner", help="only this user's jobs")
    jl.add_argument("--status", choices=STATUSES)
    jl.add_argument("--limit", type=int, default=50, help="at most this many (default 50)")
    _data_dir_arg(jl)
    jl.set_defaults(func=jobs_list)
    jp = js.add_parser("prune", help="delete finished jobs older than some days, with their files")
    jp.add_argument("--older-than", type=float, required=True, metavar="DAYS",
                    help="finished (succeeded, failed or cancelled) more than DAYS days ago")
    jp.add_argument("--owner", help="only this user's jobs")
    jp.add_argument("--dry-run", action="store_true", help="say what would go, delete nothing")
    _data_dir_arg(jp)
    jp.set_defaults(func=jobs_prune)


# -- serve -------------------------------------------------------------------------------------

@_refusing("serve")
def serve(args: argparse.Namespace) -> int:
    import logging
    import socket

    import uvicorn

    from service.app import DataDirInUse, DataDirLock, create_app
    from service.store import Store

    s = _settings(args, "host", "port", "data_dir", "backend", "redis_url", "workers", "log_level")
    logging.basicConfig(level=s.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    s.make_private()
    probe = DataDirLock(s.data_dir)
    try:
        probe.acquire()
    except DataDirInUse as e:
        raise Refused(str(e)) from None
    probe.release()
    from service.settings import redacted

    if s.backend == "rq":
        try:
            from redis import Redis

            Redis.from_url(s.redis_url, socket_connect_timeout=3).ping()
        except Exception as e:
            raise Refused(f"cannot reach Redis at {redacted(s.redis_url)}: {e}") from None

    store = Store(s.db_path)
    n_users = len(store.users())
    store.close()
    shown = socket.gethostname() if s.host in ("0.0.0.0", "::") else s.host
    url = f"http://{shown}:{s.port}"
    how = (f"{s.workers} solves at once in this process's children" if s.backend == "embedded"
           else f"solves on 'acinoset worker --redis-url {redacted(s.redis_url)}' processes")
    print(f"acinoset {_version()} serving on {url}  (API docs {url}/docs)", flush=True)
    print(f"  data dir {s.data_dir}; backend {s.backend}: {how}", flush=True)
    if n_users == 0:
        print(f"  no users yet: make a token with  acinoset users add NAME --admin --data-dir {s.data_dir}", flush=True)
    else:
        print(f"  {n_users} user(s); a new token:  acinoset users add NAME --data-dir {s.data_dir}", flush=True)
    print("  send it as the header  Authorization: Bearer TOKEN", flush=True)
    # Requests are short and solves run elsewhere: hand the GIL over sooner than the 5 ms default so a
    # status poll does not queue behind an upload being stored.
    sys.setswitchinterval(0.001)
    config = uvicorn.Config(create_app(s), host=s.host, port=s.port, log_level=s.log_level,
                            access_log=bool(args.access_log), timeout_graceful_shutdown=10,
                            limit_concurrency=s.max_connections, timeout_keep_alive=5)
    import logging

    logging.getLogger("uvicorn.access").addFilter(_hide_access_keys)
    uvicorn.Server(config).run()
    return 0


_ACCESS_KEY = re.compile(r"([?&]access=)[^&\s]*")


def _hide_access_keys(record) -> bool:
    """The access log's request line without a video link's access key (``?access=KEY`` opens the
    video to whoever holds the line): the key shown as ``***``."""
    if isinstance(record.args, tuple) and len(record.args) >= 3 and isinstance(record.args[2], str):
        args = list(record.args)
        args[2] = _ACCESS_KEY.sub(r"\1***", args[2])
        record.args = tuple(args)
    return True


def _version() -> str:
    from graph import __version__

    return __version__


# -- worker ------------------------------------------------------------------------------------

@_refusing("worker")
def worker(args: argparse.Namespace) -> int:
    import logging
    import secrets
    import socket

    from redis import Redis
    from rq import Queue
    from rq.serializers import JSONSerializer

    from service.backends.rq import project_worker_class
    from service.settings import redacted

    s = _settings(args, "redis_url", "queue_name", "log_level", "data_dir")
    os.environ["ACINOSET_DATA_DIR"] = str(s.data_dir)  # the work horses' (a shared data dir's jobs: worker.shared_job)
    logging.basicConfig(level=s.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    conn = Redis.from_url(s.redis_url)
    try:
        conn.ping()
    except Exception as e:
        raise Refused(f"cannot reach Redis at {redacted(s.redis_url)}: {e}") from None
    from service.run.worker import preload_modules, prepare_solver_environment

    prepare_solver_environment()  # work horses fork from this process
    import importlib

    for module in preload_modules(s.warm_start):  # importing service.run.warmup runs the warm-up
        try:
            importlib.import_module(module)
        except ImportError:
            pass
    queue = Queue(s.queue_name, connection=conn, serializer=JSONSerializer)
    name = args.name or f"{socket.gethostname()}.{os.getpid()}.{secrets.token_hex(2)}"
    w = project_worker_class()([queue], connection=conn, serializer=JSONSerializer, name=name, worker_ttl=WORKER_TTL,
               job_monitoring_interval=max(1, int(round(s.heartbeat_seconds))))
    print(f"acinoset worker {w.name}: taking jobs from {redacted(s.redis_url)} queue {s.queue_name}", flush=True)
    try:
        w.work(burst=bool(args.burst), logging_level=s.log_level.upper())
    except ValueError as e:
        if "exists an active worker" not in str(e):
            raise
        raise Refused(f"a worker named {name} is registered in Redis (alive, or dead for less than "
                      f"{WORKER_TTL} s): choose another --name") from None
    return 0


# -- users -------------------------------------------------------------------------------------

def _store(args: argparse.Namespace):
    from service.store import Store

    s = _settings(args, "data_dir")
    s.make_private()
    return Store(s.db_path), s


@_refusing("users add")
def users_add(args: argparse.Namespace) -> int:
    store, s = _store(args)
    user, token = store.add_user(args.name, admin=args.admin)
    print(f"added {'admin' if user.is_admin else 'user'} {user.name} to {s.data_dir}")
    print("its token (shown once; send it as 'Authorization: Bearer TOKEN'):")
    print(token)
    return 0


@_refusing("users token")
def users_token(args: argparse.Namespace) -> int:
    store, _ = _store(args)
    token = store.new_token(args.name, enable=args.enable)
    print(f"revoked the old tokens of {args.name}; the new one (shown once):")
    print(token)
    return 0


@_refusing("users remove")
def users_remove(args: argparse.Namespace) -> int:
    store, _ = _store(args)
    n = store.disable_user(args.name)
    print(f"removed {args.name}: tokens revoked, {n} active job(s) cancelled; its jobs stay for admins")
    return 0


def users_list(args: argparse.Namespace) -> int:
    import time

    store, _ = _store(args)
    rows = store.users()
    if not rows:
        print("no users (add one with 'acinoset users add NAME --admin')")
        return 0
    print(f"{'name':<24} {'role':<6} {'state':<8} {'created':<17} jobs")
    for u, counts in rows:
        jobs = ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) or "-"
        created = time.strftime("%Y-%m-%d %H:%M", time.localtime(u.created_at))
        print(f"{u.name:<24} {'admin' if u.is_admin else 'user':<6} {'removed' if u.disabled else 'active':<8} "
              f"{created:<17} {jobs}")
    return 0


# -- jobs --------------------------------------------------------------------------------------

def _job_bytes(jobs_dir: Path, job_id: str) -> int:
    """Disk use of a job's files."""
    from service.store.jobfiles import job_dir

    path = job_dir(jobs_dir, job_id)
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else 0


def _mib(n: int) -> str:
    return f"{n / 2**20:.1f} MiB"


def _owner_id(store, name: str | None) -> int | None:
    if name is None:
        return None
    user = store.user(name)
    if user is None:
        raise Refused(f"no user named {name!r}")
    return user.id


@_refusing("jobs list")
def jobs_list(args: argparse.Namespace) -> int:
    import time

    store, s = _store(args)
    jobs, total = store.jobs(_owner_id(store, args.owner), [args.status] if args.status else None,
                             limit=max(1, args.limit))
    if not jobs:
        print("no jobs")
        return 0
    print(f"{'id':<32} {'owner':<16} {'status':<10} {'method':<7} {'frames':>7} {'created':<17} {'disk':>10}")
    for job in jobs:
        created = time.strftime("%Y-%m-%d %H:%M", time.localtime(job.created_at))
        frames = (job.summary or {}).get("frames", "")
        print(f"{job.id:<32} {job.owner:<16} {job.status:<10} {job.options.get('method', ''):<7} {frames!s:>7} "
              f"{created:<17} {_mib(_job_bytes(s.jobs_dir, job.id)):>10}")
    if total > len(jobs):
        print(f"({total - len(jobs)} more; --limit to see them)")
    return 0


@_refusing("jobs prune")
def jobs_prune(args: argparse.Namespace) -> int:
    import time

    from service.core.jobs import delete_finished

    if not args.older_than >= 0:
        raise Refused("--older-than takes a number of days, 0 or more")
    store, s = _store(args)
    old = store.finished_before(time.time() - args.older_than * 86400.0, _owner_id(store, args.owner))
    freed = 0
    deleted = 0
    for job in old:
        size = _job_bytes(s.jobs_dir, job.id)
        if args.dry_run:
            freed += size
            deleted += 1
            continue
        if delete_finished(store, s.jobs_dir, job.id):  # refuses a job that became active again meanwhile
            freed += size
            deleted += 1
    verb = "would delete" if args.dry_run else "deleted"
    print(f"{verb} {deleted} finished job(s) older than {args.older_than:g} days, {_mib(freed)}")
    return 0


# The one ``acinoset`` command: the library's subcommands and the service's, composed here, where
# both layers are known (the console script in pyproject.toml points at :func:`main`).
COMMANDS: tuple[Command, ...] = (*LIBRARY_COMMANDS, *(Command(name, __name__, text) for name, text in (
    ("serve", "run the job service (REST API)"),
    ("worker", "run solves for an 'acinoset serve --backend rq' server"),
    ("users", "manage the service's users and tokens"),
    ("jobs", "list the service's jobs and prune old ones (admin)"),)))


def main(argv: list[str] | None = None) -> int:
    return cli_main(argv, COMMANDS)


if __name__ == "__main__":  # ``python -m service.cli``, as ``python -m service``
    from service.cli import main as service_main

    sys.exit(service_main())
