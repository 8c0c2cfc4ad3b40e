"""A job given its cameras' videos (``POST /v1/jobs`` with ``videos`` uploads or ``video_paths`` on
shared storage) renders the labelled videos; they stream with HTTP Range and decode with OpenCV, and
the frame picker draws one camera's frame. Against a real embedded server, with tiny simulated
footage (three cameras of the AcinoSet rig at a tenth of its resolution, 24 frames)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from servers import Redis, Server, add_user, have_redis, make_filmed_run, submit_with_videos, wait_finished, worker
from test_video import decode_cv2

pytest.importorskip("imageio_ffmpeg", reason="videos need the video extra")

FRAMES = 24


def decoded_frames(data: bytes, tmp: Path) -> list[np.ndarray]:
    """The frames OpenCV decodes from a video's bytes."""
    path = tmp / "v.mp4"
    path.write_bytes(data)
    return decode_cv2(path)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    base = tmp_path_factory.mktemp("videos")
    run, videos = make_filmed_run(base / "run", FRAMES)
    root = base / "shared"
    (root / "trial1").mkdir(parents=True)
    for v in videos:
        os.link(v, root / "trial1" / v.name)
    data = base / "data"
    data.mkdir()
    token = add_user(data, "alice")
    srv = Server(data, base / "server.log", workers=1, env=dict(os.environ, ACINOSET_VIDEO_ROOT=str(root))).start()
    with srv.client(token) as c:
        yield c, run, videos, root, srv, data
    srv.stop()


@pytest.fixture(scope="module")
def job(served):
    client, run, videos, *_ = served
    r = submit_with_videos(client, run, videos=videos)
    assert r.status_code == 202, r.text
    done = wait_finished(client, r.json()["id"], timeout=300)
    assert done["status"] == "succeeded", done
    return done


def test_uploaded_videos_yield_playable_labelled_videos(served, job, tmp_path):
    client, run, videos, *_ = served
    assert [v["frames"] for v in job["inputs"]["videos"]] == [FRAMES] * 3
    listing = client.get(job["links"]["videos"])
    assert listing.status_code == 200, listing.text
    views = {v["view"]: v["href"] for v in listing.json()["videos"]}
    assert sorted(views) == ["1", "2", "3", "3d", "combined"]
    for view, href in views.items():
        r = client.get(href, headers={"Authorization": ""})  # the access key alone opens it
        assert r.status_code == 200 and r.headers["content-type"] == "video/mp4", (view, r.status_code)
        frames = decoded_frames(r.content, tmp_path)
        assert len(frames) == FRAMES, view
    one = decoded_frames(client.get(views["1"]).content, tmp_path)
    assert one[0].shape[:2] == (152, 270)  # the footage's own size (2704x1520 at a tenth, made even)


def test_videos_answer_range_requests(served, job):
    client, *_ = served
    href = f"/v1/jobs/{job['id']}/videos/1"
    whole = client.get(href).content
    part = client.get(href, headers={"Range": "bytes=100-199"})
    assert part.status_code == 206, part.text
    assert part.content == whole[100:200]
    assert part.headers["content-range"] == f"bytes 100-199/{len(whole)}"
    # a bad Range is refused as every API error is, JSON with a detail (it was 400 text/plain)
    for bad in ("bytes=abc", "pages=1-2", "bytes=1-2,x"):
        r = client.get(href, headers={"Range": bad})
        assert r.status_code == 400 and r.headers["content-type"] == "application/json", (bad, r.text)
        assert r.json()["detail"].startswith("Range: expected bytes=START-END")
    r = client.get(href, headers={"Range": f"bytes={len(whole)}-"})
    assert r.status_code == 416 and r.headers["content-range"] == f"bytes */{len(whole)}"
    assert r.json()["detail"].startswith("Range: starts past the end")
    assert client.get(href, headers={"Range": "bytes=-100"}).content == whole[-100:]  # the last 100 bytes


def test_access_keys_open_one_job_only_and_are_checked(served, job):
    client, *_ = served
    href = client.get(job["links"]["videos"]).json()["videos"][0]["href"]
    anon = client.get(href.replace("?access=", "?access=1"), headers={"Authorization": ""})
    assert anon.status_code == 401
    other = href.replace(job["id"], "0" * 32)
    assert client.get(other, headers={"Authorization": ""}).status_code in (401, 404)
    assert client.get(f"/v1/jobs/{job['id']}/videos/7").status_code == 404


def test_a_revoked_token_closes_its_video_links(served, job):
    """A link names the token it was made for: once that token is revoked (a new one issued) or its
    user removed, the link no longer opens the video, though its signature and expiry still hold."""
    _, _, _, _, srv, data = served
    from service.store import Store

    admin_token = add_user(data, "vera", admin=True)  # an admin may see alice's job
    with srv.client(admin_token) as admin:
        href = admin.get(job["links"]["videos"]).json()["videos"][0]["href"]
    with srv.client() as anon:
        assert anon.get(href).status_code == 200
        store = Store(data / "acinoset.db")
        new_token = store.new_token("vera")
        revoked = anon.get(href)
        assert revoked.status_code == 401 and "revoked" in revoked.json()["detail"], revoked.text
        with srv.client(new_token) as admin:
            href = admin.get(job["links"]["videos"]).json()["videos"][0]["href"]
        assert anon.get(href).status_code == 200
        store.disable_user("vera")
        store.close()
        assert anon.get(href).status_code == 401


def test_frame_picker_draws_on_the_cameras_frame(served, job):
    client, run, videos, *_ = served
    r = client.get(f"/v1/jobs/{job['id']}/frame", params={"camera": 2, "n": 5})
    assert r.status_code == 200 and r.headers["content-type"] == "image/png", r.text
    png = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
    cap = cv2.VideoCapture(str(videos[1]))
    cap.set(cv2.CAP_PROP_POS_FRAMES, 5)
    ok, plain = cap.read()
    cap.release()
    assert ok and png.shape == plain.shape
    assert np.mean(np.any(np.abs(png.astype(int) - plain.astype(int)) > 40, axis=2)) > 0.001  # something drawn
    bad = client.get(f"/v1/jobs/{job['id']}/frame", params={"camera": 4, "n": 0})
    assert bad.status_code == 422 and "\n" not in bad.json()["detail"]
    assert client.get(f"/v1/jobs/{job['id']}/frame", params={"camera": 1, "n": FRAMES}).status_code == 422


def test_video_paths_under_the_root_are_used(served, tmp_path):
    client, run, videos, root, *_ = served
    paths = [f"trial1/{v.name}" for v in videos[:2]] + [str(root / "trial1" / videos[2].name)]  # relative, absolute
    r = submit_with_videos(client, run, paths=paths)
    assert r.status_code == 202, r.text
    done = wait_finished(client, r.json()["id"], timeout=300)
    assert done["status"] == "succeeded", done
    listing = client.get(done["links"]["videos"]).json()["videos"]
    assert len(decoded_frames(client.get(listing[0]["href"]).content, tmp_path)) == FRAMES


def test_paths_outside_the_root_are_refused(served, tmp_path):
    client, run, videos, root, *_ = served
    outside = str(videos[0])  # a real video, but not under the root
    link = root / "escape.mp4"
    link.symlink_to(videos[0])  # a link inside the root that leads out of it
    for bad in (outside, "../run/" + videos[0].name, "escape.mp4", "/etc/passwd"):
        r = submit_with_videos(client, run, paths=[bad, f"trial1/{videos[1].name}", f"trial1/{videos[2].name}"])
        assert r.status_code == 403, (bad, r.text)
        assert "\n" not in r.json()["detail"] and str(root) not in r.json()["detail"]


def test_a_count_mismatch_and_a_non_video_are_refused(served):
    client, run, videos, *_ = served
    r = submit_with_videos(client, run, videos=videos[:2])
    assert r.status_code == 422 and "2 videos for 3 keypoint files" in r.json()["detail"], r.text
    r = submit_with_videos(client, run, videos=[videos[0], videos[1], run.cams[0]])
    assert r.status_code == 422 and "\n" not in r.json()["detail"], r.text
    both = submit_with_videos(client, run, videos=videos, paths=[f"trial1/{v.name}" for v in videos])
    assert both.status_code == 422


def test_a_server_without_a_root_refuses_any_path_and_videos_count_in_the_upload_limit(tmp_path, served):
    _, run, videos, *_ = served
    data = tmp_path / "data"
    data.mkdir()
    token = add_user(data, "bob")
    no_videos = sum(p.stat().st_size for p in [*run.cams, run.calibration])
    limit = no_videos + 10_000  # room for the keypoints and calibration, not for the videos as well
    assert sum(v.stat().st_size for v in videos) > 10_000
    srv = Server(data, tmp_path / "server.log", workers=1, env={"ACINOSET_MAX_UPLOAD_BYTES": str(limit)}).start()
    try:
        with srv.client(token) as c:
            r = submit_with_videos(c, run, paths=[str(v) for v in videos])
            assert r.status_code == 403 and "ACINOSET_VIDEO_ROOT" in r.json()["detail"], r.text
            r = submit_with_videos(c, run, videos=videos)
            assert r.status_code == 413 and "\n" not in r.json()["detail"], r.text
    finally:
        srv.stop()


@pytest.mark.skipif(not have_redis(), reason="needs Debian's redis-server (.ci/run installs it)")
def test_rq_workers_render_the_videos_and_send_them_back(tmp_path, served):
    """With RQ the uploaded videos travel to the worker in the job's input archive and the labelled
    videos come back in its result archive."""
    _, run, videos, *_ = served
    data = tmp_path / "data"
    data.mkdir()
    token = add_user(data, "carol")
    redis = Redis(tmp_path / "redis", tmp_path / "redis.log").start()
    srv = w = None
    try:
        srv = Server(data, tmp_path / "server.log", backend="rq", redis_url=redis.url).start()
        w = worker(redis.url, tmp_path / "worker.log", "w1").start()
        with srv.client(token) as c:
            r = submit_with_videos(c, run, videos=videos)
            assert r.status_code == 202, r.text
            done = wait_finished(c, r.json()["id"], timeout=300)
            assert done["status"] == "succeeded", done
            listing = c.get(done["links"]["videos"]).json()["videos"]
            assert [v["view"] for v in listing] == ["1", "2", "3", "3d", "combined"]
            for v in listing:
                assert len(decoded_frames(c.get(v["href"]).content, tmp_path)) == FRAMES, v["view"]
    finally:
        for p in (w, srv, redis):
            if p is not None:
                p.stop()


def test_videos_that_cannot_be_rendered_leave_the_solve_standing_with_a_warning(served, tmp_path):
    """The worker's render step: a video the renderer refuses (here one of 5 frames for a 24-frame
    run, past the checks at submission) costs the job its videos, not its solve."""
    from graph.video import FrameWriter, YuvFrame
    from service.run.worker import ThrottledProgress, solve_job
    from service.store import jobfiles

    _, run, videos, *_ = served
    short = tmp_path / "short.mp4"
    with FrameWriter(short, 64, 48, 30.0) as w:
        for _ in range(5):
            w.write(YuvFrame(64, 48))
    inp = tmp_path / "input"
    (inp / "keypoints").mkdir(parents=True)
    for c, p in enumerate(run.cams):
        d = jobfiles.keypoints_dir(inp, c)
        d.mkdir(parents=True)
        (d / p.name).write_bytes(p.read_bytes())
    (inp / "calibration").mkdir()
    (inp / "calibration" / "calibration.toml").write_bytes(run.calibration.read_bytes())
    jobfiles.write_manifest(inp, {
        "keypoints": [f"keypoints/{c + 1:02d}/{p.name}" for c, p in enumerate(run.cams)],
        "calibration": "calibration/calibration.toml", "skeleton": None,
        "options": {"method": "tri", "fps": run.fps}, "video_paths": [str(videos[0]), str(short), str(videos[2])]})
    stages = []
    report = solve_job(inp, tmp_path / "out", ThrottledProgress(lambda s, *a: stages.append(s) or True, 0.0))
    said = [w for w in report["warnings"] if "labelled videos could not be rendered" in w]
    assert len(said) == 1 and "short.mp4" in said[0] and "5 frames" in said[0], report["warnings"]
    assert json.loads((tmp_path / "out" / "report.json").read_text())["warnings"] == report["warnings"]
    assert not (tmp_path / "out" / "videos").exists()
    assert "rendering videos" in stages and (tmp_path / "out" / "result.h5").is_file()
