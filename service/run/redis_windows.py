"""A long job's windows shared with RQ workers (:mod:`service.run.shared_windows`) through Redis.

The parent is the job's RQ work horse; a helper is :func:`service.run.worker.run_rq_job` again, given
``helper_of`` (the one function the workers run), enqueued on the job's queue once for each idle
worker. A helper reads the job's input files as the parent did (from Redis, or on the data dir the
workers share) and stages them.

Redis keys, each under ``acinoset:windows:<token>`` and expiring with the job's timeout:

* ``:plan`` (JSON), ``:claims`` (a hash, window -> who, set once with ``HSETNX``), ``:next``, ``:stop``;
* ``:alive:<helper>``: a helper's heartbeat, expiring after :data:`~service.run.shared_windows.BEAT_TTL_S`;
* ``:done:<k>``: window k's result, a zip of its files (:func:`~service.run.shared_windows.write_window`)
  in chunks (:func:`service.store.jobfiles.put_archive`);
* ``:staging``: on a data dir the workers share, who stages each camera's file (camera -> ``parent``
  or the helper's name, set once), the run's cameras staged once between them in the parent's result
  folder (:func:`stage_together`); ``together`` set when the parent asks its helpers to (without it,
  a helper stages a copy of its own, as it does when the files travel through Redis).
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from service.run.shared_windows import (
    BEAT_TTL_S,
    PARENT,
    POLL_S,
    WINDOW_FILES,
    SharedWindows,
    read_window,
    worker_of,
    write_window,
)

TOGETHER = "together"  # in ``:staging``: the helpers stage the cameras with the work horse


class Keys:
    """The Redis keys of one job's shared windows (module docstring)."""

    def __init__(self, token: str):
        from service.store.jobfiles import windows_key

        self.base = windows_key(token)
        self.plan, self.claims, self.next, self.stop, self.staging = (
            f"{self.base}:{k}" for k in ("plan", "claims", "next", "stop", "staging"))

    def alive(self, who: str) -> str:
        return f"{self.base}:alive:{who}"

    def done(self, k: int) -> str:
        return f"{self.base}:done:{k}"


def _text(value) -> str | None:
    """A Redis reply as text (None stays None)."""
    return value.decode() if isinstance(value, bytes) else value


def _running(redis, token: str) -> bool:
    """Whether the parent's RQ job is still running (a parent killed says no ``stop`` of its own)."""
    from rq.exceptions import InvalidJobOperation, NoSuchJobError
    from rq.job import Job as RQJob
    from rq.serializers import JSONSerializer

    try:
        return RQJob.fetch(token, connection=redis, serializer=JSONSerializer).get_status(refresh=False) == "started"
    except (NoSuchJobError, InvalidJobOperation):
        return False


class RedisBoard:
    """The :class:`~service.run.shared_windows.Board` of the RQ job ``token`` in Redis (module
    docstring); every key expires after ``ttl`` seconds (the job's timeout)."""

    def __init__(self, redis, token: str, ttl: int):
        self.redis, self.token, self.keys, self.ttl = redis, token, Keys(token), int(ttl)

    def publish(self, plan: dict, windows: int, me: str) -> None:
        r, k_ = self.redis, self.keys
        r.delete(k_.claims, k_.next, *(k_.done(k) for k in range(windows)))  # a retried job's results are not reused
        r.set(k_.next, 0, ex=self.ttl)
        r.hset(k_.claims, "-1", me)  # the hash exists, so that its expiry holds
        r.expire(k_.claims, self.ttl)
        r.set(k_.plan, json.dumps(plan), ex=self.ttl)

    def plan(self) -> dict | None:
        raw = self.redis.get(self.keys.plan)
        return None if raw is None else json.loads(raw)

    def claim(self, k: int, who: str) -> bool:
        got = bool(self.redis.hsetnx(self.keys.claims, str(k), who))
        if got:
            self.redis.expire(self.keys.claims, self.ttl)  # should the parent have deleted it meanwhile
        return got

    def owner(self, k: int) -> str | None:
        return _text(self.redis.hget(self.keys.claims, str(k)))

    def take_over(self, k: int, who: str) -> None:
        self.redis.hset(self.keys.claims, str(k), who)

    def all_claimed(self, windows: int) -> bool:
        return int(self.redis.hlen(self.keys.claims)) > windows  # every window, and the parent's marker

    def set_next(self, k: int) -> None:
        self.redis.set(self.keys.next, k, ex=self.ttl)

    def next(self) -> int:
        return int(self.redis.get(self.keys.next) or 0)

    def put(self, k: int, result, valid: np.ndarray) -> None:
        from service.store.jobfiles import pack_files, put_archive

        with tempfile.TemporaryDirectory(prefix="acinoset-window-") as tmp:
            write_window(Path(tmp), result, valid)
            put_archive(self.redis, self.keys.done(k), pack_files(Path(tmp), list(WINDOW_FILES)), ttl=self.ttl)

    def take(self, k: int) -> tuple[Any, np.ndarray] | None:
        from service.store.jobfiles import get_archive, unpack_files

        archive = get_archive(self.redis, self.keys.done(k))
        if archive is None:
            return None
        self.redis.delete(self.keys.done(k))
        with tempfile.TemporaryDirectory(prefix="acinoset-window-") as tmp:
            unpack_files(archive, Path(tmp), WINDOW_FILES)
            return read_window(Path(tmp))

    def finished(self, k: int) -> bool:
        return bool(self.redis.exists(self.keys.done(k)))

    def beat(self, who: str) -> None:
        self.redis.set(self.keys.alive(who), 1, ex=int(BEAT_TTL_S))

    def alive(self, who: str) -> bool:
        return bool(self.redis.exists(self.keys.alive(who)))

    def leave(self, who: str) -> None:
        self.redis.delete(self.keys.alive(who))

    def stop(self) -> None:
        self.redis.set(self.keys.stop, 1, ex=self.ttl)

    def stopped(self) -> bool:
        return bool(self.redis.exists(self.keys.stop))

    def parent_running(self) -> bool:
        return _running(self.redis, self.token)

    def clear(self, windows: int) -> None:
        from service.store.jobfiles import PARTIAL

        k_ = self.keys
        self.redis.delete(k_.plan, k_.claims, k_.next, k_.staging, *(k_.done(k) for k in range(windows)),
                          *(k_.done(k) + PARTIAL for k in range(windows)))


class RQSharedWindows(SharedWindows):
    """The windows of an RQ job shared through :class:`RedisBoard`; ``shared``: the workers share the
    data dir, so the helpers invited before staging stage the cameras with the work horse, each
    camera once (:func:`stage_together`)."""

    def __init__(self, board: RedisBoard, me: str, enqueue, idle, drop, shared: bool = False):
        super().__init__(board, me, enqueue, idle, drop)
        self.redis_board, self.shared = board, shared

    def _stage_with_helpers(self, before_staging: bool) -> bool:
        r, k_ = self.redis_board.redis, self.redis_board.keys
        r.delete(k_.stop, k_.staging)  # a retried job's cameras are staged again
        if not (self.shared and before_staging):
            return False
        r.hset(k_.staging, TOGETHER, 1)
        r.expire(k_.staging, self.redis_board.ttl)
        return True

    def stage(self, paths: list[str], folder: Path, read):
        """The run's cameras staged with the helpers (:func:`stage_together`); ``staged``: each
        worker's cameras."""
        b = self.redis_board
        run = stage_together(b.redis, b.token, PARENT, paths, folder, read, b.ttl)
        for c in range(len(paths)):
            owner = _text(b.redis.hget(b.keys.staging, str(c)))
            if owner is not None:
                self.staged[worker_of(owner, self.me)] += 1
        return run


# a camera claimed only while the cameras are staged together (the parent's ``together`` there): 1 claimed,
# 0 someone else's, -1 the staging is over (the job ended, its keys gone)
_CLAIM = """
if redis.call('HEXISTS', KEYS[1], ARGV[3]) == 0 then return -1 end
return redis.call('HSETNX', KEYS[1], ARGV[1], ARGV[2])
"""
# a camera taken over from a claimant that is gone, only if it is still that one's (one taker wins)
_TAKE_OVER = """
if redis.call('HGET', KEYS[1], ARGV[1]) == ARGV[2] then redis.call('HSET', KEYS[1], ARGV[1], ARGV[3]) return 1 end
return 0
"""


def stage_together(redis, token: str, me: str, paths: list[str], folder: Path, read, ttl: int):
    """The job's cameras ``paths`` staged in ``folder`` (made by the work horse before it invited the
    helpers), on the data dir the workers share, by the job's work horse and its helpers between
    them: each camera claimed by one (``:staging``, set once while ``together`` is there; ``me`` is
    :data:`PARENT` for the work horse) and staged by it (:func:`graph.io.staged.stage_camera`), the
    others waited for; a camera whose claimant is gone (a helper's heartbeat expired, the job no longer
    running) is taken over by one of those waiting (compare and set) and staged again. The run
    (:meth:`graph.io.staged.StagedRun.gather`), or None: a file holds several individuals, or (a
    helper's) the job ended or stopped first; RuntimeError when the work horse finds its staging
    keys gone."""
    from graph.io.staged import StagedRun, stage_camera

    k_ = Keys(token)
    claim, take_over = redis.register_script(_CLAIM), redis.register_script(_TAKE_OVER)

    def ended() -> bool:
        if me == PARENT:
            return False
        return bool(redis.exists(k_.stop)) or not _running(redis, token) or not folder.is_dir()

    def over() -> None:
        if me == PARENT:
            raise RuntimeError("the job's staging keys are gone from Redis (expired, or deleted)")

    for c, path in enumerate(paths):
        if ended():
            return None
        got = claim(keys=[k_.staging], args=[str(c), me, TOGETHER])
        if got == -1:
            return over()
        if got == 1:
            redis.expire(k_.staging, ttl)
            stage_camera(path, folder, c, read)
    run = StagedRun(folder)
    while missing := run.unstaged(len(paths)):
        if ended():
            return None
        for c in missing:
            owner = _text(redis.hget(k_.staging, str(c)))
            if owner is None:
                return over()
            gone = not _running(redis, token) if owner == PARENT else not redis.exists(k_.alive(owner))
            if gone and take_over(keys=[k_.staging], args=[str(c), owner, me]) == 1:
                stage_camera(paths[c], folder, c, read)
        time.sleep(POLL_S)
    return StagedRun.gather(folder, len(paths))
