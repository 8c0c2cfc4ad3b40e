"""``acinoset serve`` and ``acinoset users`` as an admin uses them (through ``service.cli``, the
``acinoset`` entry point)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import httpx
from servers import PY, ROOT, Proc, acinoset, free_port, submit_ok, wait_answering, wait_dead, wait_for, wait_solving


def serve(data: str, log: Path) -> tuple[Proc, str]:
    """``acinoset serve`` with only the flags an admin gives (port, data dir, workers), once it
    answers; the process and its URL."""
    port = free_port()
    server = Proc([PY, "-m", "service", "serve", "--port", str(port), "--data-dir", data, "--workers", "1"],
                  log).start()
    url = f"http://127.0.0.1:{port}"
    try:
        wait_answering(url, server, ready=(200,))
    except BaseException:
        server.stop()
        raise
    return server, url


def test_serve_and_users_as_an_admin_would(tmp_path, long_run):
    data = str(tmp_path / "data")
    added = acinoset("users", "add", "kim", "--admin", "--data-dir", data)
    assert added.returncode == 0, added.stderr
    kim = added.stdout.strip().splitlines()[-1]
    assert kim.startswith("acn_") and " " not in kim
    lee = acinoset("users", "add", "lee", "--data-dir", data).stdout.strip().splitlines()[-1]
    again = acinoset("users", "add", "lee", "--data-dir", data)
    assert again.returncode == 2 and "already exists" in again.stderr and again.stderr.count("\n") == 1

    server, url = serve(data, tmp_path / "serve.log")
    try:
        banner = server.log()
        assert f"serving on {url}" in banner and "Authorization: Bearer TOKEN" in banner
        assert "acinoset users add NAME" in banner

        # one data dir, one server
        second = acinoset("serve", "--port", str(free_port()), "--data-dir", data)
        assert second.returncode == 2 and "another acinoset server is using" in second.stderr

        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {lee}"}, timeout=60) as c:
            listed = acinoset("users", "list", "--data-dir", data).stdout
            assert "kim" in listed and "admin" in listed and "lee" in listed

            # a new token revokes the old one
            assert c.get("/v1/jobs").status_code == 200
            new_lee = acinoset("users", "token", "lee", "--data-dir", data).stdout.strip().splitlines()[-1]
            assert c.get("/v1/jobs").status_code == 401
            c.headers["Authorization"] = f"Bearer {new_lee}"
            assert c.get("/v1/jobs").json()["total"] == 0

            # one solve running, one queued behind it (one worker): both active when the user goes,
            # the command line's call the only thing between the solve starting and the removal
            running = submit_ok(c, long_run, {"method": "fte", "skeleton": "cheetah"})
            queued = submit_ok(c, long_run, {"method": "fte", "skeleton": "cheetah"})
            pid = int(wait_solving(c, running)["worker"].rsplit(":", 1)[1])

            # removing a user revokes its token and stops its jobs, even from the command line
            removed = acinoset("users", "remove", "lee", "--data-dir", data)
            assert removed.returncode == 0 and "2 active job(s) cancelled" in removed.stdout
            assert c.get("/v1/jobs").status_code == 401
            assert wait_dead(pid, 10), "the removed user's solve still runs"
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {kim}"}, timeout=60) as admin:
            for j in (running, queued):
                job = wait_for(admin, j, lambda x: x["status"] == "cancelled", 10)
                assert job["owner"] == "lee"
    finally:
        server.stop()


def test_the_compose_file_runs_an_api_two_workers_and_a_durable_redis_behind_a_password():
    """Redis publishes no port and needs a password (security issue 25: it published 6379 on every
    interface with none, and whoever reaches it can queue work for the workers); every service gets
    the password through its environment, none on a command line."""
    import yaml

    doc = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
    services = doc["services"]
    redis = services["redis"]
    assert "ports" not in redis and "--appendonly yes" in redis["command"][-1]
    assert '--requirepass "$$ACINOSET_REDIS_PASSWORD"' in redis["command"][-1]
    assert redis["environment"]["ACINOSET_REDIS_PASSWORD"].startswith("${ACINOSET_REDIS_PASSWORD:?")
    api = services["api"]["command"]
    assert api[:2] == ["acinoset", "serve"] and "rq" in api and not any("redis://" in a for a in api)
    workers = [s for s in services.values() if s.get("command", [])[:2] == ["acinoset", "worker"]]
    assert len(workers) == 2
    for s in [services["api"], *workers]:
        url = s["environment"]["ACINOSET_REDIS_URL"]
        assert url.startswith("redis://:${ACINOSET_REDIS_PASSWORD:?") and url.endswith("@redis:6379/0")
    assert [p for s in services.values() for p in s.get("ports", [])] == ["8000:8000"]
    # the workers mount the API's data dir, which it shares with them: no job's files through Redis
    assert services["api"]["environment"]["ACINOSET_SHARED_DATA_DIR"] == "1"
    for s in [services["api"], *workers]:
        assert s["volumes"] == ["acinoset-data:/data"] and s["environment"]["ACINOSET_DATA_DIR"] == "/data"
    dockerfile = (ROOT / "docker" / "Dockerfile").read_text()
    assert "pip install ." in dockerfile and 'CMD ["acinoset", "serve"' in dockerfile


def test_an_admin_lists_and_prunes_old_jobs_while_the_server_runs(tmp_path, small_run):
    data = str(tmp_path / "data")
    ana = acinoset("users", "add", "ana", "--data-dir", data).stdout.strip().splitlines()[-1]
    server, url = serve(data, tmp_path / "serve.log")
    try:
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {ana}"}, timeout=60) as c:
            done = [submit_ok(c, small_run, {"method": "tri", "skeleton": "points"}) for _ in range(2)]
            for j in done:
                wait_for(c, j, lambda x: x["status"] == "succeeded", 120)

            listed = acinoset("jobs", "list", "--data-dir", data)
            assert listed.returncode == 0, listed.stderr
            rows = [line for line in listed.stdout.splitlines() if line.split()[0] in done]
            assert len(rows) == 2 and all("ana" in r and "succeeded" in r and "MiB" in r for r in rows)

            # nothing is a day old yet; a dry run with 0 days names both and deletes nothing
            kept = acinoset("jobs", "prune", "--older-than", "1", "--data-dir", data)
            assert kept.returncode == 0 and "deleted 0 finished job(s)" in kept.stdout
            dry = acinoset("jobs", "prune", "--older-than", "0", "--dry-run", "--data-dir", data)
            assert "would delete 2 finished job(s)" in dry.stdout
            assert all(c.get(f"/v1/jobs/{j}").status_code == 200 for j in done)

            pruned = acinoset("jobs", "prune", "--older-than", "0", "--data-dir", data)
            assert pruned.returncode == 0 and "deleted 2 finished job(s)" in pruned.stdout
            assert all(c.get(f"/v1/jobs/{j}").status_code == 404 for j in done)
            assert not any((tmp_path / "data" / "jobs" / j).exists() for j in done)

            nobody = acinoset("jobs", "prune", "--older-than", "0", "--owner", "zed", "--data-dir", data)
            assert nobody.returncode == 2 and nobody.stderr.strip() == "acinoset jobs prune: no user named 'zed'"
    finally:
        server.stop()


def test_the_data_dir_is_private_and_users_token_keeps_a_removed_user_out(tmp_path):
    """Issue item 11: the data dir was created with the umask's rights (0755, files 0644), and
    ``users token`` silently re-enabled a removed user."""
    import stat

    data = tmp_path / "data"
    assert acinoset("users", "add", "max", "--data-dir", str(data)).returncode == 0
    mode = lambda p: stat.S_IMODE(p.stat().st_mode)  # noqa: E731
    assert mode(data) == 0o700 and mode(data / "jobs") == 0o700 and mode(data / "acinoset.db") == 0o600
    assert acinoset("users", "remove", "max", "--data-dir", str(data)).returncode == 0
    refused = acinoset("users", "token", "max", "--data-dir", str(data))
    assert refused.returncode == 2 and "was removed; give --enable" in refused.stderr, refused
    back = acinoset("users", "token", "max", "--enable", "--data-dir", str(data))
    assert back.returncode == 0 and back.stdout.strip().splitlines()[-1].startswith("acn_")
    # a data dir made before, with wider rights, is narrowed when the server starts
    old = tmp_path / "old"
    (old / "jobs").mkdir(parents=True)
    old.chmod(0o755)
    from servers import Server
    srv = Server(old, tmp_path / "server.log", workers=1, env={"ACINOSET_WARM_START": "0"}).start()
    try:
        assert mode(old) == 0o700 and mode(old / "acinoset.db") == 0o600
        files = [p for p in old.rglob("*") if p.is_file()]
        assert files and all(mode(p) & 0o077 == 0 for p in files), [(p.name, oct(mode(p))) for p in files]
    finally:
        srv.stop()


def test_the_access_log_hides_video_access_keys(tmp_path):
    """--access-log logged each request line whole: a video link's ?access=KEY opens that video to
    whoever reads the log (security issue 25, minor). The key is shown as ***."""
    port = free_port()
    log = tmp_path / "serve.log"
    server = Proc([PY, "-m", "service", "serve", "--port", str(port), "--data-dir", str(tmp_path / "data"),
                   "--workers", "1", "--access-log"], log).start()
    url = f"http://127.0.0.1:{port}"
    try:
        wait_answering(url, server, ready=(200, 503))
        key = "k" + os.urandom(12).hex()
        httpx.get(f"{url}/v1/jobs/{'0' * 32}/videos/1?access={key}&x=1", timeout=30)
        deadline = time.time() + 10
        while "videos/1" not in server.log() and time.time() < deadline:
            time.sleep(0.1)
    finally:
        server.stop()
    text = server.log()
    assert f"/v1/jobs/{'0' * 32}/videos/1?access=***&x=1" in text, text[-2000:]
    assert key not in text
