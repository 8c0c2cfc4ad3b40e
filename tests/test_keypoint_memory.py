"""The keypoint readers in bounded memory: files that declare huge dimensions, and a few hundred
mutants of valid files, read in a subprocess whose address space is capped (``resource.setrlimit``).

Every file must be read or refused with one :class:`~graph.errors.InputError` line; a MemoryError,
a RecursionError or any other exception fails. Before the readers checked dimensions first, a 12 KB
H5 declaring 2,000,000 x 60 took the reader to 2.5 GB and a 200 MB CSV to 4.5 GB.
"""

from __future__ import annotations

import json
import pickle
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
from test_keypoints import _columns, _detections, _h5py_fixed, _h5py_table, _Pickled, _set_attrs

MEMORY_CAP = 1 << 30  # bytes of address space for the reading process (imports take about 160 MB)
MAX_FRAMES, MAX_BODYPARTS = 50_000, 100  # the service's defaults

READER = r"""
import json, resource, sys, warnings
resource.setrlimit(resource.RLIMIT_AS, (int(sys.argv[1]), int(sys.argv[1])))
warnings.simplefilter("ignore")
from graph.errors import InputError
from graph.io.keypoints import ReadLimits, read_keypoints
limits = ReadLimits(max_frames=int(sys.argv[2]), max_bodyparts=int(sys.argv[3]))
out = {}
for path in sys.argv[4:]:
    try:
        kp = read_keypoints(path, limits=limits)
        out[path] = ["read", kp.frames, len(kp.bodyparts)]
    except InputError as e:
        out[path] = ["refused", type(e).__name__, str(e)]
    except BaseException as e:
        out[path] = ["crashed", type(e).__name__, str(e)[:300]]
print(json.dumps(out))
"""


def _read_capped(paths: list[Path]) -> dict:
    r = subprocess.run([sys.executable, "-c", READER, str(MEMORY_CAP), str(MAX_FRAMES), str(MAX_BODYPARTS),
                        *map(str, paths)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return {Path(k).name: v for k, v in json.loads(r.stdout).items()}


def _bombs(d: Path) -> dict[str, str]:
    """Small files declaring what would not fit in the cap, and the refusal each must get."""
    cols = _columns([f"bp{i}" for i in range(20)])
    _h5py_fixed(d / "fixed_rows.h5", cols, np.zeros((2, 60)))
    with h5py.File(d / "fixed_rows.h5", "r+") as f:  # 2,000,000 x 60 float64 (960 MB), unwritten: 12 KB
        del f["df_with_missing/block0_values"]
        f["df_with_missing"].create_dataset("block0_values", shape=(2_000_000, 60), dtype="f8",
                                            chunks=(20_000, 60), compression="gzip")
    _h5py_fixed(d / "fixed_labels.h5", cols, np.zeros((2, 60)))
    with h5py.File(d / "fixed_labels.h5", "r+") as f:  # a column label list of 100 million codes
        del f["df_with_missing/axis0_label2"]
        f["df_with_missing"].create_dataset("axis0_label2", shape=(100_000_000,), dtype="i1", chunks=(1 << 20,),
                                            compression="gzip")
    dtype = np.dtype([("index", "<i8"), ("values_block_0", "<f8", (60,))])
    with h5py.File(d / "table_rows.h5", "w") as f:
        g = f.create_group("df_with_missing")
        _set_attrs(g, {"pandas_type": b"frame_table", "table_type": b"appendable_frame"})
        t = g.create_dataset("table", shape=(2_000_000,), dtype=dtype, chunks=(10_000,), compression="gzip")
        _set_attrs(t, {"CLASS": b"TABLE", "values_block_0_kind": _Pickled(pickle.dumps(cols, protocol=0))})
    strings = np.dtype([("index", "<i8"), ("values_block_0", "S20000", (60,))])
    with h5py.File(d / "table_strings.h5", "w") as f:  # 50,000 rows of 60 strings of 20 kB, unwritten: 60 GB
        g = f.create_group("df_with_missing")
        _set_attrs(g, {"pandas_type": b"frame_table", "table_type": b"appendable_frame"})
        t = g.create_dataset("table", shape=(50_000,), dtype=strings, chunks=(64,), compression="gzip")
        _set_attrs(t, {"CLASS": b"TABLE", "values_block_0_kind": _Pickled(pickle.dumps(cols, protocol=0))})
    _h5py_fixed(d / "fixed_level_bytes.h5", cols, np.zeros((2, 60)))
    with h5py.File(d / "fixed_level_bytes.h5", "r+") as f:  # 100 labels of 10 MB each, unwritten: 1 GB
        del f["df_with_missing/axis0_level1"]
        f["df_with_missing"].create_dataset("axis0_level1", shape=(100,), dtype="S10000000", chunks=(1,),
                                            compression="gzip")
    wide = 3 * 100_000  # 100,000 bodyparts in one header: every GET of such a job was megabytes
    (d / "wide.csv").write_text("scorer" + ",s" * wide + "\nbodyparts" + "".join(f",b{j // 3}" for j in range(wide))
                                + "\ncoords" + ",x,y,likelihood" * (wide // 3) + "\n0" + ",1" * wide + "\n")
    row = ",812.25,433.5,0.5" * 20 + "\n"
    with open(d / "long.csv", "w") as f:  # 60,000 frames: over the frame limit, refused while streaming
        f.write("scorer" + ",s" * 60 + "\nbodyparts" + "".join(f",b{j // 3}" for j in range(60))
                + "\ncoords" + ",x,y,likelihood" * 20 + "\n")
        f.writelines(f"{i}{row}" for i in range(60_000))
    nested = pickle.dumps([("s", "nose", "x")] + [([[[[[[[[[["x"]]]]]]]]]],)], protocol=0)
    # one column label (scorer, <a list nested 20,000 deep>, coord): str() of it was a RecursionError
    deep = b"((S's'\n" + b"(" * 20_000 + b"l" * 20_000 + b"S'x'\ntl."
    _h5py_table(d / "nested_label.h5", _columns(["nose"]), np.zeros((3, 3)), kind_attr=nested)
    _h5py_table(d / "deep_label.h5", _columns(["nose"]), np.zeros((3, 3)), kind_attr=deep)
    return {"fixed_rows.h5": "2000000 frames", "fixed_labels.h5": "bodyparts", "table_rows.h5": "2000000 frames",
            "wide.csv": "longer than", "long.csv": "more than 50000 frames", "nested_label.h5": "MultiIndex",
            "deep_label.h5": "labels", "table_strings.h5": "not numbers",
            "fixed_level_bytes.h5": "10000000 bytes each; at most 4096"}


def _mutants(d: Path, count: int, seed: int = 7) -> list[Path]:
    """Valid CSV and H5 files with bytes flipped, runs deleted or duplicated, or cut short."""
    rng = np.random.default_rng(seed)
    values = _detections(n=40).reshape(40, -1)
    cols = _columns(["nose", "l_eye", "r_eye", "neck_base"])
    _h5py_fixed(d / "valid_fixed.h5", cols, values)
    _h5py_table(d / "valid_table.h5", cols, values)
    text = "scorer" + "".join(f",{c[0]}" for c in cols) + "\nbodyparts" + "".join(f",{c[1]}" for c in cols) + \
        "\ncoords" + "".join(f",{c[2]}" for c in cols) + "\n" + \
        "".join(f"{i}," + ",".join("" if v != v else repr(v) for v in row) + "\n" for i, row in enumerate(values))
    (d / "valid.csv").write_text(text)
    sources = [(d / n).read_bytes() for n in ("valid.csv", "valid_fixed.h5", "valid_table.h5")]
    out = []
    for k in range(count):
        data = bytearray(sources[k % 3])
        kind = rng.integers(4)
        if kind == 0:  # flip bytes
            for at in rng.integers(0, len(data), rng.integers(1, 20)):
                data[at] = rng.integers(256)
        elif kind == 1:  # delete a run
            a = int(rng.integers(0, len(data)))
            del data[a: a + int(rng.integers(1, 200))]
        elif kind == 2:  # duplicate a run
            a = int(rng.integers(0, len(data)))
            data[a:a] = data[a: a + int(rng.integers(1, 400))] * int(rng.integers(1, 50))
        else:  # cut short
            del data[int(rng.integers(1, len(data))):]
        path = d / f"mutant{k:03d}{('.csv', '.h5', '.h5')[k % 3]}"
        path.write_bytes(bytes(data))
        out.append(path)
    return out


def test_files_declaring_huge_dimensions_are_refused_within_the_memory_cap(tmp_path):
    expected = _bombs(tmp_path)
    got = _read_capped([tmp_path / n for n in expected])
    for name, words in expected.items():
        verdict = got[name]
        assert verdict[0] == "refused", (name, verdict)
        assert words in verdict[2], (name, verdict)
        assert "\n" not in verdict[2] and verdict[2].startswith(name), (name, verdict)
    assert got["fixed_rows.h5"][1] == got["long.csv"][1] == "TooLargeInput"


def test_mutated_files_are_read_or_refused_in_one_line_within_the_memory_cap(tmp_path):
    paths = _mutants(tmp_path, 300)
    got = _read_capped(paths)
    crashed = {k: v for k, v in got.items() if v[0] == "crashed"}
    assert not crashed, crashed
    assert all("\n" not in v[2] for v in got.values() if v[0] == "refused")
    # the mutations are not all fatal: some files still read, many are refused
    kinds = [v[0] for v in got.values()]
    assert kinds.count("read") > 10 and kinds.count("refused") > 10, kinds
