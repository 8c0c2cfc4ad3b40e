"""One long job over several RQ workers: its windows shared with the workers that are idle.

A long run is solved in windows (:mod:`graph.solve.windows`): what every frame shares is settled
once, then each window is solved on its own with those values held, and the windows' kept frames
are written in order. On the RQ backend the job's work horse (the *parent*) settles the run, writes
the *plan* into Redis and enqueues one *helper* RQ job for each worker that is idle (the same queue
and job function: a helper is :func:`service.run.worker.run_rq_job` given ``helper_of``). A helper
reads the job's input files from Redis as the parent did, stages them, and solves windows until
none is left; the parent solves windows too while it waits, and takes the windows in order.

Redis keys, each under ``acinoset:windows:<token>`` and expiring with the job's timeout:

* ``:plan``: JSON ``{"options", "sigma_px", "settled_on", "spans"}`` (the held options, the noise,
  the settled stretch, each window's frames ``[lo, hi)``);
* ``:claims``: a hash, window -> who solves it (the parent's worker, or a helper's RQ job and worker,
  ``<job>@<worker>``), set once (``HSETNX``);
* ``:alive:<helper>``: a helper's heartbeat, refreshed every :data:`BEAT_S` seconds; a window whose
  helper's heartbeat has expired (:data:`BEAT_TTL_S`) is solved by the parent instead;
* ``:next``: the window the parent takes next; a helper claims windows at most :data:`LOOKAHEAD`
  after it, so that at most ``LOOKAHEAD + 1`` results wait in Redis, and the parent holds at most
  ``LOOKAHEAD`` windows it solved ahead (a window's Result: about 11 MB at 2,400 frames of six
  cameras and 20 markers);
* ``:done:<k>``: window k's result, a zip of its ``result.h5`` (:func:`graph.io.results.write_h5`)
  and ``valid.npy`` (the confident detections) in chunks (:func:`service.store.jobfiles.put_archive`);
* ``:stop``: set when the parent ends; a helper stops at its next window;
* ``:staging``: on a data dir the workers share, who stages each camera's file (camera -> ``parent``
  or the helper's name, set once), the run's cameras staged once between them in the parent's result
  folder (:func:`stage_together`); ``together`` set when the parent asks its helpers to (without it,
  a helper stages a copy of its own, as it does when the files travel through Redis).

The answer does not depend on who solved which window when the workers run the same build on the
same kind of CPU (tested on one machine): a window's result is a function of the run's frames and the
plan (the same inputs staged the same way), and its arrays travel as float64 in HDF5. Workers of
other builds or CPUs may round differently, window by window. A helper leaves when other jobs wait in
the queue (a long job does not hold idle workers from them). Nothing from Redis is unpickled.
"""

from __future__ import annotations

import dataclasses
import json
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

BEAT_S = 2.0  # a helper's heartbeat period
BEAT_TTL_S = 30.0  # a heartbeat older than this: the helper is gone (a long kernel call may delay a beat)
LOOKAHEAD = 6  # windows a helper may solve past the one the parent takes next (results waiting in Redis)
POLL_S = 0.05


PARENT = "parent"  # who staged a camera (``:staging``), when the job's own work horse did
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


def _pack(result, valid: np.ndarray) -> bytes:
    from graph.io.results import write_h5
    from service.store.jobfiles import pack_files

    with tempfile.TemporaryDirectory(prefix="acinoset-window-") as tmp:
        write_h5(Path(tmp) / "result.h5", result)
        np.save(Path(tmp) / "valid.npy", valid, allow_pickle=False)
        return pack_files(Path(tmp), ["result.h5", "valid.npy"])


def _unpack(archive: bytes):
    from graph.io.results import read_result
    from service.store.jobfiles import unpack_files

    with tempfile.TemporaryDirectory(prefix="acinoset-window-") as tmp:
        unpack_files(archive, Path(tmp), ("result.h5", "valid.npy"))
        return read_result(Path(tmp) / "result.h5"), np.load(Path(tmp) / "valid.npy", allow_pickle=False)


def _options_json(options) -> dict:
    from graph.types import jsonable

    return jsonable(dataclasses.asdict(options))


def _options_from(d: dict, skeleton: str):
    """The plan's held options, with this process's own path of the job's skeleton file."""
    from pydantic import TypeAdapter

    from graph.types import SolveOptions

    return TypeAdapter(SolveOptions).validate_python({**d, "skeleton": skeleton})


class SharedWindows:
    """The parent's side: a :data:`graph.solve.windows.WindowSolver` that shares the windows with
    helpers (module docstring). ``me`` names the parent's worker; ``enqueue(n)`` starts ``n``
    helpers and returns their RQ jobs' ids; ``idle()`` counts the workers free to help; ``ttl``
    bounds how long any key outlives the job; ``shared``: the workers share the data dir (the cameras
    can be staged together, :meth:`invite`). ``solved``: each worker's windows, once done; ``staged``:
    each worker's cameras, when staged together."""

    def __init__(self, redis, token: str, me: str, enqueue, idle, ttl: int, shared: bool = False):
        self.redis, self.token, self.keys, self.me = redis, token, Keys(token), me
        self.enqueue, self.idle, self.ttl, self.shared = enqueue, idle, int(ttl), shared
        self.helpers: list[str] = []
        self.invited = False
        self.together = False
        self.solved: Counter[str] = Counter()
        self.staged: Counter[str] = Counter()

    def __call__(self, source, spans: list[tuple[int, int]], settled) -> Iterator[tuple[Any, Any]]:
        from graph.solve.windows import solve_window

        r, k_ = self.redis, self.keys
        n = len(spans)
        options, sigma_px = settled.options, settled.sigma_px
        r.delete(k_.claims, k_.next, *(k_.done(k) for k in range(n)))  # a retried job's results are not reused
        r.set(k_.next, 0, ex=self.ttl)
        r.hset(k_.claims, "-1", self.me)  # the hash exists, so that its expiry holds
        r.expire(k_.claims, self.ttl)
        r.set(k_.plan, json.dumps({"options": _options_json(options), "sigma_px": float(sigma_px),
                                   "settled_on": [settled.start, settled.stop],
                                   "spans": [list(s) for s in spans]}), ex=self.ttl)
        self.invite(n)
        ahead: dict[int, tuple[Any, Any]] = {}

        def mine(k: int) -> tuple[Any, Any]:
            self.solved[self.me] += 1
            lo, hi = spans[k]
            return solve_window(source, lo, hi, options, sigma_px)

        try:
            for k in range(n):
                r.set(k_.next, k, ex=self.ttl)
                yield self._take(k, n, ahead, mine)
        finally:
            r.set(k_.stop, 1, ex=self.ttl)
            self._end(n)

    def invite(self, windows: int, before_staging: bool = False) -> None:
        """Enqueue a helper for each idle worker, at most ``windows - 1``, once. Called as soon as the
        run is known to be long (before it is settled), so that the helpers stage the run meanwhile
        and wait for the plan; called again when the windows start, it does nothing. Invited
        ``before_staging`` on a shared data dir, the helpers stage the run's cameras with this work
        horse, each camera once (:func:`stage_together`; ``together`` then says so); otherwise each
        stages a copy of its own."""
        if self.invited:
            return
        self.invited = True
        k_ = self.keys
        self.redis.delete(k_.stop, k_.staging)  # a retried job's cameras are staged again
        helpers = min(max(0, self.idle()), windows - 1)
        if helpers > 0:
            self.together = self.shared and before_staging
            if self.together:
                self.redis.hset(k_.staging, TOGETHER, 1)
                self.redis.expire(k_.staging, self.ttl)
            self.helpers = list(self.enqueue(helpers))

    def stage(self, paths: list[str], folder: Path, read):
        """The run's cameras staged with the helpers (:func:`stage_together`); ``staged``: each
        worker's cameras."""
        run = stage_together(self.redis, self.token, PARENT, paths, folder, read, self.ttl)
        for c in range(len(paths)):
            owner = _text(self.redis.hget(self.keys.staging, str(c)))
            if owner is not None:
                self.staged[self._worker(owner)] += 1
        return run

    def close(self) -> None:
        """The run ended (solved, failed, or found short): the helpers invited stop, those not started
        are dropped."""
        if self.invited:
            from redis.exceptions import RedisError

            try:
                self.redis.set(self.keys.stop, 1, ex=self.ttl)
                self._end(0)
            except RedisError:  # Redis gone: the keys expire with the job's timeout, the helpers with the parent
                pass

    def _take(self, k: int, n: int, ahead: dict, mine) -> tuple[Any, Any]:
        """Window k: solved ahead here, done by a helper, claimed now and solved here, or (its helper
        gone) taken over; while its helper works, a later window is solved here meanwhile."""
        from service.store.jobfiles import get_archive

        r, k_ = self.redis, self.keys
        while True:
            if k in ahead:
                return ahead.pop(k)
            archive = get_archive(r, k_.done(k))
            if archive is not None:
                r.delete(k_.done(k))
                self.solved[self._worker(self._owner(k))] += 1
                return _unpack(archive)
            if r.hsetnx(k_.claims, str(k), self.me):
                return mine(k)
            who = self._owner(k)
            if who == self.me or not r.exists(k_.alive(who)):
                if r.exists(k_.done(k)):  # finished as its heartbeat ran out
                    continue
                r.hset(k_.claims, str(k), self.me)  # its helper is gone: solved here
                return mine(k)
            j = next((j for j in range(k + 1, min(n, k + 1 + LOOKAHEAD)) if j not in ahead
                      and not r.hexists(k_.claims, str(j))), None)
            if j is not None and r.hsetnx(k_.claims, str(j), self.me):
                ahead[j] = mine(j)
                continue
            time.sleep(POLL_S)

    def _worker(self, claimant: str) -> str:
        """The worker a claim names: this one's for the parent's, ``<job>@<worker>``'s for a helper's."""
        return self.me if claimant == PARENT else claimant.rpartition("@")[2]

    def _owner(self, k: int) -> str:
        """Who claimed window k."""
        return str(_text(self.redis.hget(self.keys.claims, str(k))))

    def _end(self, n: int) -> None:
        """The helpers not started are dropped; the keys go (a helper still solving finds ``stop``
        and its result expires with the job's timeout)."""
        from rq.job import Job as RQJob
        from rq.serializers import JSONSerializer

        from service.store.jobfiles import PARTIAL

        for jid in self.helpers:
            try:
                rj = RQJob.fetch(jid, connection=self.redis, serializer=JSONSerializer)
                if rj.get_status() in ("queued", "deferred", "scheduled"):
                    rj.delete()
            except Exception:  # noqa: BLE001 - gone already
                pass
        k_ = self.keys
        self.redis.delete(k_.plan, k_.claims, k_.next, k_.staging, *(k_.done(k) for k in range(n)),
                          *(k_.done(k) + PARTIAL for k in range(n)))


def _running(redis, token: str) -> bool:
    """Whether the parent's RQ job is still running (a parent killed says no ``stop`` of its own)."""
    from rq.exceptions import InvalidJobOperation, NoSuchJobError
    from rq.job import Job as RQJob
    from rq.serializers import JSONSerializer

    try:
        return RQJob.fetch(token, connection=redis, serializer=JSONSerializer).get_status(refresh=False) == "started"
    except (NoSuchJobError, InvalidJobOperation):
        return False


def _plan(redis, token: str) -> dict | None:
    """The plan, once the parent has written it; None if the parent stops or ends first."""
    k_ = Keys(token)
    while True:
        raw = redis.get(k_.plan)
        if raw is not None:
            return json.loads(raw)
        if redis.exists(k_.stop) or not _running(redis, token):
            return None
        time.sleep(0.2)


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


def _text(value) -> str | None:
    """A Redis reply as text (None stays None)."""
    return value.decode() if isinstance(value, bytes) else value


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


def help_with_windows(redis, token: str, me: str, stage, calibration, options, others_waiting) -> int:
    """A helper's side: the job's run staged (``stage()``, a :class:`graph.io.staged.StagedRun` or
    None: a copy of its own, or :func:`stage_together` on a shared data dir; its heartbeat beats
    meanwhile), then the windows of the job whose RQ token is ``token`` solved until none is left to
    claim, the parent stops, or ``others_waiting()`` says other jobs wait for a worker; ``me`` names it
    in the claims (``<its RQ job>@<its worker>``), ``calibration`` and ``options`` are the job's.
    Returns the windows it solved."""
    from graph.solve.windows import Staged, solve_window
    from service.store.jobfiles import put_archive

    k_ = Keys(token)
    stopped = threading.Event()

    def beat() -> None:
        while not stopped.is_set():
            redis.set(k_.alive(me), 1, ex=int(BEAT_TTL_S))
            stopped.wait(BEAT_S)

    redis.set(k_.alive(me), 1, ex=int(BEAT_TTL_S))  # alive before its first claim
    beating = threading.Thread(target=beat, name="window-helper-heartbeat", daemon=True)
    beating.start()
    try:
        run = stage()
        plan = None if run is None else _plan(redis, token)
        if plan is None:
            return 0
        ttl = max(60, int(redis.ttl(k_.plan)))
        held = _options_from(plan["options"], options.skeleton)
        spans = [(int(lo), int(hi)) for lo, hi in plan["spans"]]
        source = Staged(run, calibration, options)
        s0, s1 = plan["settled_on"]
        source.stretch(int(s0), int(s1), dataclasses.replace(options, window_frames=0))  # the windows' template
        solved = 0
        while not redis.exists(k_.stop) and _running(redis, token):  # a parent killed sets no stop
            if others_waiting() or not redis.exists(k_.plan):  # the parent ended: its claims are gone
                break
            nxt = int(redis.get(k_.next) or 0)
            k = next((j for j in range(nxt, min(len(spans), nxt + 1 + LOOKAHEAD))
                      if redis.hsetnx(k_.claims, str(j), me)), None)
            redis.expire(k_.claims, ttl)  # should the parent have deleted it meanwhile
            if k is None:
                if redis.hlen(k_.claims) > len(spans):
                    break  # every window claimed (and the parent's marker)
                time.sleep(POLL_S)
                continue
            lo, hi = spans[k]
            result, valid = solve_window(source, lo, hi, held, float(plan["sigma_px"]))
            put_archive(redis, k_.done(k), _pack(result, valid), ttl=ttl)
            solved += 1
        return solved
    finally:
        stopped.set()
        beating.join(timeout=BEAT_S + 1)
        redis.delete(k_.alive(me))
