"""``POST /v1/batches`` with hostile Anipose projects, against a real embedded server: a project is
read from its own archive only (paths out of it are refused, naming the key), in a helper process
under time and memory limits, with linear-time patterns, bounded walks and one-line 4xx answers that
name no path of the server."""

from __future__ import annotations

import io
import json
import struct
import threading
import time
import zipfile
from pathlib import Path

import httpx
import pytest
from servers import ROOT, Server, add_user, server_with_users

pytest.importorskip("tables")

TOP = "p"  # the archive's one top folder


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("hostile_data")
    srv = server_with_users(data, data.parent / "hostile_server.log")
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """One session, one trial on three cameras (A, B, C), 20 frames, plain triangulation."""
    from graph.anipose.simulate import write_project

    return write_project(tmp_path_factory.mktemp("hostile_project") / TOP, sessions={"s1": ["run1"]}, frames=20,
                         optim=False)


@pytest.fixture(scope="module")
def bob_job(server, base) -> str:
    """Bob's job from the same project, solved: its inputs and report are in the data dir."""
    with server.client(server.tokens["bob"]) as bob:
        r = post(bob, archive(base))
        assert r.status_code == 202, r.text
        (trial,) = r.json()["trials"]
        deadline = time.monotonic() + 120
        while bob.get(trial["link"]).json()["status"] in ("queued", "running"):
            assert time.monotonic() < deadline, "bob's job did not finish"
            time.sleep(0.2)
        assert bob.get(trial["link"]).json()["status"] == "succeeded"
        return trial["job_id"]


@pytest.fixture
def alice(server):
    with server.client(server.tokens["alice"]) as c:
        yield c


# -- building projects ---------------------------------------------------------------------------

def config(base: Path, top: str = "", acinoset: str = "", tables: str = "", replace: dict | None = None) -> str:
    """The base project's config.toml with top-level keys ``top``, lines added to ``[acinoset]``,
    tables appended and lines replaced."""
    text = (base / "config.toml").read_text(encoding="utf-8")
    for old, new in (replace or {}).items():
        assert old in text, old
        text = text.replace(old, new)
    text = text.replace("[acinoset]\n", "[acinoset]\n" + acinoset + "\n")
    return f"{top}\n{text}\n{tables}\n"


def archive(base: Path, cfg: str | None = None, extra: dict[str, bytes] | None = None) -> bytes:
    """The base project zipped under its top folder, with ``cfg`` as its config.toml and ``extra``
    entries (names relative to the top folder)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for p in sorted(base.rglob("*")):
            rel = p.relative_to(base).as_posix()
            if p.is_file() and not (cfg is not None and rel == "config.toml"):
                z.write(p, f"{TOP}/{rel}")
        if cfg is not None:
            z.writestr(f"{TOP}/config.toml", cfg)
        for name, data in (extra or {}).items():
            z.writestr(f"{TOP}/{name}", data)
    return buf.getvalue()


def raw_zip(entries: list[tuple[str, bytes]], method: int = zipfile.ZIP_STORED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as z:
        for name, data in entries:
            z.writestr(name, data)
    return buf.getvalue()


def post(client: httpx.Client, data: bytes, options: dict | None = None, timeout: float = 120) -> httpx.Response:
    return client.post("/v1/batches", files={"project": ("project.zip", data, "application/zip")},
                       data={"options": json.dumps(options or {})}, timeout=timeout)


def clean(r: httpx.Response, server: Server) -> dict:
    """The answer's body, checked: no internal error, no path of the server (its data dir or checkout)."""
    assert r.status_code < 500, r.text
    assert "internal error" not in r.text
    assert str(server.data_dir) not in r.text and str(ROOT) not in r.text, r.text
    return r.json()


def refused(r: httpx.Response, server: Server, *fragments: str) -> str:
    assert r.status_code == 422, r.text
    detail = clean(r, server)["detail"]
    for f in fragments:
        assert f in detail, detail
    return detail


# -- confinement: every path a project names is in its archive ---------------------------------------

def test_path_out_of_the_archive_lists_nobody_elses_jobs(server, alice, base, bob_job):
    """``path`` naming the jobs dir with ``nesting = -1`` once listed every user's job folders."""
    cfg = config(base, top=f'path = "{server.data_dir / "jobs"}"', replace={"nesting = 1": "nesting = -1"},
                 tables='[pipeline]\npose_2d = "."\ncalibration_results = "."')
    r = post(alice, archive(base, cfg))
    body = clean(r, server)
    assert bob_job not in r.text
    assert r.status_code == 202, r.text
    assert all(t["trial"].startswith("s1/") for t in body["trials"]), body["trials"]  # the archive's own
    assert any("path" in n and "upload" in n for n in body["notes"]), body["notes"]


def test_another_users_calibration_is_refused(server, alice, base, bob_job):
    cal = server.data_dir / "jobs" / bob_job / "input" / "calibration"
    assert (cal / "calibration.toml").is_file()
    r = post(alice, archive(base, config(base, tables=f'[pipeline]\ncalibration_results = "{cal}"')))
    refused(r, server, "[pipeline] calibration_results", "outside")


def test_another_users_fitted_smoothing_is_refused(server, alice, base, bob_job):
    report = server.data_dir / "jobs" / bob_job / "result" / "report.json"
    assert report.is_file()
    r = post(alice, archive(base, config(base, acinoset=f'motion_scale = "{report}"')))
    refused(r, server, "[acinoset] motion_scale", "outside")


def test_a_skeleton_reached_by_dots_is_refused(server, alice, base):
    """The check was lexical: ``<project>/../../..`` was taken for a file of the project."""
    target = ROOT / "graph" / "skeletons" / "cheetah.toml"
    assert target.is_file()
    dots = "../" * 14 + str(target).lstrip("/")
    r = post(alice, archive(base, config(base, acinoset=f'skeleton = "{dots}"')))
    refused(r, server, "[acinoset] skeleton", "outside")
    r = post(alice, archive(base), options={"skeleton": dots})  # the options field names the same file
    refused(r, server, "options: skeleton", "outside")


def test_a_skeleton_in_the_archive_is_still_taken(server, alice, base):
    skeleton = (ROOT / "graph" / "skeletons" / "cheetah.toml").read_bytes()
    r = post(alice, archive(base, config(base, acinoset='skeleton = "rig/cheetah.toml"'),
                            extra={"rig/cheetah.toml": skeleton}))
    assert r.status_code == 202, r.text
    (trial,) = clean(r, server)["trials"]
    assert trial["job_id"], trial
    assert alice.get(trial["link"]).json()["inputs"]["skeleton"]["name"] == "cheetah.toml"


def test_a_body_file_outside_is_no_existence_oracle(server, alice, base):
    """A file that exists (not JSON) and one that does not once got different answers."""
    details = []
    for name in ("/etc/passwd", "/nonexistent-acinoset/body.json"):
        r = post(alice, archive(base, config(base, acinoset=f'body = "{name}"')))
        details.append(refused(r, server, "[acinoset] body", "outside"))
    assert details[0] == details[1]


def test_a_missing_project_path_names_no_server_folder(server, alice, base):
    """``path`` that does not exist here: the note once named the server's data dir."""
    r = post(alice, archive(base, config(base, top='path = "/nonexistent/x"')))
    assert r.status_code == 202, r.text
    body = clean(r, server)
    assert body["trials"][0]["job_id"], body


def test_walking_usr_is_bounded(server, alice, base):
    """``path = "/usr"`` with ``nesting = -1`` once never answered (it followed /usr/bin/X11 -> .)."""
    cfg = config(base, top='path = "/usr"', replace={"nesting = 1": "nesting = -1"})
    t0 = time.monotonic()
    r = post(alice, archive(base, cfg), timeout=30)
    assert time.monotonic() - t0 < 30
    body = clean(r, server)
    assert r.status_code == 202, r.text
    assert [t["trial"] for t in body["trials"]] == ["s1/pose-2d/run1"] or \
        all(t["trial"].startswith("s1") for t in body["trials"]), body["trials"]


# -- patterns in linear time ------------------------------------------------------------------------

def test_a_catastrophic_cam_regex_does_not_stall_the_server(server, alice, base):
    """``_((a+)+)$`` against ``x_aaa...a!``: backtracking took the API's GIL for seconds."""
    cfg = config(base, replace={"cam_regex = '_([A-Z])$'": "cam_regex = '_((a+)+)$'"})
    data = archive(base, cfg, extra={"s1/pose-2d/x_" + "a" * 28 + "!.h5": b"not read"})
    out: dict = {}

    def submit() -> None:
        t0 = time.monotonic()
        out["response"] = post(alice, data, timeout=60)
        out["seconds"] = time.monotonic() - t0

    thread = threading.Thread(target=submit)
    thread.start()
    time.sleep(0.3)
    t0 = time.monotonic()
    assert httpx.get(server.url + "/healthz", timeout=30).status_code in (200, 503)  # answering (503: compiling)
    health = time.monotonic() - t0
    thread.join(60)
    assert health < 2.0, f"/healthz took {health:.1f} s while the batch was read"  # it took 28 s
    assert out["seconds"] < 10, out
    refused(out["response"], server, "no trials")


def test_a_pattern_re2_cannot_run_is_refused_by_name(server, alice, base):
    cfg = config(base, replace={"cam_regex = '_([A-Z])$'": r"cam_regex = '_([A-Z])\1$'"})
    refused(post(alice, archive(base, cfg)), server, "[triangulation] cam_regex")


# -- the upload -------------------------------------------------------------------------------------

def _peak_rss(pid: int) -> int:
    status = Path(f"/proc/{pid}/status").read_text()
    return int(next(line for line in status.splitlines() if line.startswith("VmHWM:")).split()[1]) * 1024


def test_the_archive_is_not_read_into_memory(server, alice, base):
    """A 60 MB archive once raised the API process's peak memory by about as much."""
    import os

    big = os.urandom(60 * 2**20)  # incompressible, stored
    buf = io.BytesIO(archive(base))
    with zipfile.ZipFile(buf, "a", zipfile.ZIP_STORED) as z:
        z.writestr(f"{TOP}/s1/videos-raw/big.bin", big)
    data = buf.getvalue()
    del big
    Path(f"/proc/{server.pid}/clear_refs").write_text("5")  # the peak starts again from now
    before = _peak_rss(server.pid)
    r = post(alice, data)
    assert r.status_code == 202, r.text
    grew = _peak_rss(server.pid) - before
    assert grew < 20 * 2**20, f"the API process's peak memory grew by {grew / 2**20:.0f} MiB"


# -- answers that were 500 ---------------------------------------------------------------------------

def _patch_method(data: bytes, method: int) -> bytes:
    """Every entry's compression method set to ``method`` (local and central headers)."""
    b = bytearray(data)
    for sig, at in ((b"PK\x03\x04", 8), (b"PK\x01\x02", 10)):
        i = b.find(sig)
        while i >= 0:
            b[i + at:i + at + 2] = struct.pack("<H", method)
            i = b.find(sig, i + 4)
    return bytes(b)


def _bad_crc(base: Path) -> bytes:
    payload = b"calibration data " * 64
    data = raw_zip([(f"{TOP}/config.toml", (base / "config.toml").read_bytes()), (f"{TOP}/s1/notes.txt", payload)])
    i = data.find(payload)
    return data[:i] + b"X" + data[i + 1:]


BAD_ARCHIVES = {
    "file and folder of one name": lambda base: raw_zip([(f"{TOP}/config.toml", b'cam_regex = "x"'),
                                                          (f"{TOP}/s1", b"a file"), (f"{TOP}/s1/x.h5", b"x")]),
    "a name of 300 characters": lambda base: raw_zip([(f"{TOP}/config.toml", b""), (f"{TOP}/{'a' * 300}.h5", b"x")]),
    "a path of 4200 characters": lambda base: raw_zip([(f"{TOP}/config.toml", b""),
                                                        (f"{TOP}/" + ("b" * 199 + "/") * 21 + "x.h5", b"x")]),
    "a bad CRC": _bad_crc,
    "compression method 99": lambda base: _patch_method(raw_zip([(f"{TOP}/config.toml", b"x = 1")]), 99),
}


@pytest.mark.parametrize("case", list(BAD_ARCHIVES))
def test_a_malformed_archive_is_422(server, alice, base, case):
    refused(post(alice, BAD_ARCHIVES[case](base)), server, "project")


BAD_CONFIGS = {
    "arrays 50,000 deep": ("nested too deeply", {"top": "deep = " + "[" * 50_000 + "]" * 50_000}),
    "score_threshold of 401 digits": ("score_threshold", {"replace": {"score_threshold = 0.5":
                                                                      "score_threshold = 1" + "0" * 400}}),
    "offset of 401 digits": ("offset", {"tables": f"[cameras.A]\noffset = [1{'0' * 400}, 0]"}),
    "constraints = 5": ("constraints", {"replace": {"constraints = [": "constraints = 5\nx = ["}}),
    "skeleton = 5": ("skeleton", {"acinoset": "skeleton = 5"}),
    "pose_2d = 5": ("pose_2d", {"tables": "[pipeline]\npose_2d = 5"}),
}


@pytest.mark.parametrize("case", list(BAD_CONFIGS))
def test_a_malformed_config_is_422(server, alice, base, case):
    key, edit = BAD_CONFIGS[case]
    refused(post(alice, archive(base, config(base, **edit))), server, key)


# -- what held already ---------------------------------------------------------------------------------

def test_traversal_links_and_bombs_are_still_refused(server, alice, base):
    r = post(alice, raw_zip([(f"{TOP}/config.toml", b""), (f"{TOP}/../../escaped.txt", b"x")]))
    refused(r, server, "outside")
    assert not (server.data_dir / "escaped.txt").exists()

    link = zipfile.ZipInfo(f"{TOP}/s1/calibration/link.toml")
    link.external_attr = (0o120777 << 16)  # a symbolic link to /etc/passwd
    buf = io.BytesIO(archive(base))
    with zipfile.ZipFile(buf, "a") as z:
        z.writestr(link, "/etc/passwd")
    refused(post(alice, buf.getvalue()), server, "link")

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as z:
        z.writestr(f"{TOP}/config.toml", b"")
        with z.open(f"{TOP}/zeros.bin", "w", force_zip64=True) as f:
            for _ in range(600):
                f.write(bytes(2**20))
    r = post(alice, buf.getvalue())
    assert r.status_code == 413 and "upload limit" in clean(r, server)["detail"], r.text


def test_cross_user_answers_hold(server, alice, bob_job):
    assert alice.get(f"/v1/jobs/{bob_job}").status_code == 404


# -- the reader's limits -----------------------------------------------------------------------------

def test_a_project_read_past_the_time_limit_is_stopped(tmp_path, base):
    """The reader is a process of its own, killed at its wall-clock limit; the server answers on."""
    data = tmp_path / "data"
    data.mkdir()
    token = add_user(data, "carol")
    srv = Server(data, tmp_path / "server.log", env={"ACINOSET_BATCH_READ_TIMEOUT_SECONDS": "0.01"}).start()
    try:
        with srv.client(token) as carol:
            t0 = time.monotonic()
            r = post(carol, archive(base))
            assert time.monotonic() - t0 < 10
            refused(r, srv, "longer than", "ACINOSET_BATCH_READ_TIMEOUT_SECONDS")
            assert carol.get("/healthz", timeout=2).status_code in (200, 503)  # answering (503: still compiling)
            assert carol.get("/v1/jobs").json()["jobs"] == []
    finally:
        srv.stop()


def _allocate(n: int) -> int:
    return len(bytearray(n))


def _spin() -> None:
    while True:
        pass


def _sleep(seconds: float) -> None:
    time.sleep(seconds)


def test_the_reader_process_is_held_to_its_limits():
    """:func:`service.run.batch_reader.run_limited`, the process a batch's project is read in: its value,
    or a one-line refusal naming the limit it passed (memory, CPU time, wall clock)."""
    from service.errors import Unprocessable
    from service.run.batch_reader import run_limited

    limits = {"timeout": 60.0, "memory_bytes": 2**30, "cpu_seconds": 30.0}
    assert run_limited(_allocate, {"n": 2**20}, **limits) == 2**20
    with pytest.raises(Unprocessable, match="ACINOSET_BATCH_READ_MEMORY_BYTES"):
        run_limited(_allocate, {"n": 4 * 2**30}, **limits)
    with pytest.raises(Unprocessable, match="ACINOSET_BATCH_READ_CPU_SECONDS"):
        run_limited(_spin, {}, **{**limits, "cpu_seconds": 1.0})
    t0 = time.monotonic()
    with pytest.raises(Unprocessable, match="ACINOSET_BATCH_READ_TIMEOUT_SECONDS"):
        run_limited(_sleep, {"seconds": 60.0}, **{**limits, "timeout": 3.0})
    assert time.monotonic() - t0 < 10
    with pytest.raises(Unprocessable, match="not a zip archive"):  # a JobError raised in it is raised here
        from service.run.batch_reader import unpack

        run_limited(unpack, {"archive": Path("/nonexistent.zip"), "dest": Path("/nonexistent"), "max_bytes": 1},
                    **limits)
