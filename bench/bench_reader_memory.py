"""Peak memory of the keypoint readers on files that declare or hold a lot, each read in a fresh
process (peak RSS from ``getrusage``), with the service's limits and without any.

Files: a 12 KB H5 declaring 2,000,000 x 60 (fixed and table layouts), a CSV with 100,000
bodyparts in its header, a 200 MB CSV (576,690 frames x 20 bodyparts) and the largest CSV the
service's default limits take (50,000 frames x 100 bodyparts, 85 MB).

    python bench/bench_reader_memory.py [--out bench/results/reader_memory.json]
"""

from __future__ import annotations

import argparse
import json
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_keypoints import _columns, _h5py_fixed, _Pickled, _set_attrs  # noqa: E402

PROBE = r"""
import json, resource, sys, time, warnings
warnings.simplefilter("ignore")
from graph.io.keypoints import ReadLimits, read_keypoints
limits = ReadLimits(50_000, 100) if sys.argv[2] == "limits" else ReadLimits()
t = time.perf_counter()
try:
    kp = read_keypoints(sys.argv[1], limits=limits)
    said = f"read {kp.frames} frames x {len(kp.bodyparts)} bodyparts"
except Exception as e:
    said = f"{type(e).__name__}: {e}"
print(json.dumps({"result": said, "seconds": time.perf_counter() - t,
                  "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def make_files(d: Path) -> list[Path]:
    cols = _columns([f"bp{i}" for i in range(20)])
    _h5py_fixed(d / "fixed_2e6x60.h5", cols, np.zeros((2, 60)))
    with h5py.File(d / "fixed_2e6x60.h5", "r+") as f:
        del f["df_with_missing/block0_values"]
        f["df_with_missing"].create_dataset("block0_values", shape=(2_000_000, 60), dtype="f8", chunks=(20_000, 60),
                                            compression="gzip")
    dtype = np.dtype([("index", "<i8"), ("values_block_0", "<f8", (60,))])
    with h5py.File(d / "table_2e6x60.h5", "w") as f:
        g = f.create_group("df_with_missing")
        _set_attrs(g, {"pandas_type": b"frame_table", "table_type": b"appendable_frame"})
        t = g.create_dataset("table", shape=(2_000_000,), dtype=dtype, chunks=(10_000,), compression="gzip")
        _set_attrs(t, {"CLASS": b"TABLE", "values_block_0_kind": _Pickled(pickle.dumps(cols, protocol=0))})
    wide = 3 * 100_000
    (d / "wide_1e5_bodyparts.csv").write_text(
        "scorer" + ",s" * wide + "\nbodyparts" + "".join(f",b{j // 3}" for j in range(wide))
        + "\ncoords" + ",x,y,likelihood" * (wide // 3) + "\n0" + ",1" * wide + "\n")

    def csv(path: Path, bodyparts: int, frames: int) -> None:
        with open(path, "w") as f:
            f.write("scorer" + ",s" * 3 * bodyparts
                    + "\nbodyparts" + "".join(f",b{j // 3}" for j in range(3 * bodyparts))
                    + "\ncoords" + ",x,y,likelihood" * bodyparts + "\n")
            row = ",812.25,433.5,0.5" * bodyparts + "\n"
            f.writelines(f"{i}{row}" for i in range(frames))

    csv(d / "big_200MB.csv", 20, 576_690)
    csv(d / "largest_legal_5e4x100.csv", 100, 50_000)
    return sorted(d.iterdir())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for path in make_files(Path(tmp)):
            for mode in ("limits", "none"):
                if mode == "none" and path.suffix == ".h5":
                    continue  # without limits these read 1 GB of zeros: the 'before' row says what that cost
                r = subprocess.run([sys.executable, "-c", PROBE, str(path), mode], cwd=ROOT, capture_output=True,
                                   text=True, timeout=900)
                row = {"file": path.name, "bytes": path.stat().st_size, "limits": mode, **json.loads(r.stdout)}
                row["result"] = row["result"].replace(str(path.parent) + "/", "")
                print(json.dumps(row))
                out.append(row)
    if args.out:
        args.out.write_text(json.dumps({"rows": out}, indent=2) + "\n")


if __name__ == "__main__":
    main()
