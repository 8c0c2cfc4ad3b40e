"""The library stands alone: graph/ imports, solves and draws with the service unimportable, and the
command line's help and version load neither the server nor the solvers."""

import subprocess
import sys
import textwrap

BLOCK_SERVICE = textwrap.dedent("""
    import sys
    class NoService:
        def find_spec(self, name, path=None, target=None):
            if name == "service" or name.startswith("service."):
                raise ImportError("the service is not installed here")
            return None
    sys.meta_path.insert(0, NoService())
""")


def _python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)


def test_the_library_works_without_the_service(tmp_path):
    code = BLOCK_SERVICE + textwrap.dedent(f"""
        import graph.api, graph.app.cli, graph.io.results, graph.viewer.playback
        from graph.io.calibration import default_rig_path, load_calibration
        from graph.simulate import simulate_run
        from graph.types import SolveOptions
        cal = load_calibration(default_rig_path())
        run = simulate_run(cal, frames=20, seed=0)
        result = graph.api.solve(run.keypoints, cal, SolveOptions(method="tri", fps=run.fps))
        html = graph.viewer.playback.playback_html(result)
        assert "AcinoResultView" in html and "AcinoDom" in html
        graph.io.results.write_h5({str(tmp_path / 'r.h5')!r}, result)
        assert graph.app.cli.main(["plot", {str(tmp_path / 'r.h5')!r}, "--out", {str(tmp_path / 'pics')!r}]) == 0
        assert not any(m == "service" or m.startswith("service.") for m in sys.modules)
        print("ok")
    """)
    proc = _python(code)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("ok"), proc.stderr[-2000:]
    assert (tmp_path / "pics" / "playback.html").is_file()


def test_help_and_version_load_neither_the_server_nor_the_solvers():
    code = textwrap.dedent("""
        import sys
        from service.cli import main
        for argv in (["--help"], ["--version"], ["solve", "--help"]):
            try:
                main(argv)
            except SystemExit:
                pass
        heavy = [m for m in ("gtsam", "numba", "fastapi", "uvicorn", "service.app", "graph.api", "cv2", "h5py")
                 if m in sys.modules]
        print("loaded:", heavy)
    """)
    proc = _python(code)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "loaded: []"
