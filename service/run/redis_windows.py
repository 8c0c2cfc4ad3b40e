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
  folder (:func:`~service.run.shared_windows.stage_together`); ``together`` set when the parent asks its
  helpers to (without it, a helper stages a copy of its own, as it does when the files travel through
  Redis). A camera is claimed by a Lua script that claims only while ``together`` is there.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from service.run.shared_windows import BEAT_TTL_S, WINDOW_FILES, read_window, write_window

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
    docstring); every key expires after ``ttl`` seconds (the job's timeout). ``shared``: the workers
    share the data dir, so the helpers can stage the cameras with the work horse."""

    def __init__(self, redis, token: str, ttl: int, shared: bool = False):
        self.redis, self.token, self.keys, self.ttl, self.shared = redis, token, Keys(token), int(ttl), shared

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

    def begin(self) -> None:
        self.redis.delete(self.keys.stop, self.keys.staging)  # a retried job keeps its token: its cameras staged again

    def together(self, before_staging: bool) -> bool:
        r, k_ = self.redis, self.keys
        if not (self.shared and before_staging):
            return False
        r.hset(k_.staging, TOGETHER, 1)
        r.expire(k_.staging, self.ttl)
        return True

    def staging_together(self) -> bool:
        return bool(self.redis.hexists(self.keys.staging, TOGETHER))

    def claim_camera(self, c: int, who: str) -> int:
        got = int(self.redis.register_script(_CLAIM)(keys=[self.keys.staging], args=[str(c), who, TOGETHER]))
        if got == 1:
            self.redis.expire(self.keys.staging, self.ttl)
        return got

    def camera_owner(self, c: int) -> str | None:
        return _text(self.redis.hget(self.keys.staging, str(c)))

    def take_over_camera(self, c: int, owner: str, who: str) -> bool:
        return self.redis.register_script(_TAKE_OVER)(keys=[self.keys.staging], args=[str(c), owner, who]) == 1


# a camera claimed only while the cameras are staged together (``together`` in ``:staging``): 1 claimed,
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
