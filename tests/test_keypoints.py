"""DeepLabCut keypoint files: every layout DeepLabCut writes, read without unpickling, and
one-line errors for bad files.

Files are made the way DeepLabCut makes them: a pandas DataFrame with the (scorer, [individuals,]
bodyparts, coords) column MultiIndex, saved with ``to_csv`` and with
``to_hdf(path, key="df_with_missing", format="table", mode="w")`` (``analyze_videos``) or the
default fixed format. Where pandas/PyTables are not installed, the fixed and table layouts are
written with h5py (``_h5py_fixed`` / ``_h5py_table``), and the tests that have pandas check that
those files match what pandas writes.
"""

from __future__ import annotations

import pickle
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest

from graph.errors import InputError
from graph.io.keypoints import (
    Keypoints,
    _literal_unpickle,
    check_same_frames,
    match_bodyparts,
    read_keypoints,
    select_markers,
    write_dlc_csv,
)

SCORER = "DLC_resnet50_cheetahJun1shuffle1_200000"
BODYPARTS = ["nose", "l_eye", "r_eye", "neck_base"]


def _detections(n: int = 12, m: int = len(BODYPARTS), seed: int = 3) -> np.ndarray:
    """(N, M, 3) x, y, likelihood as DeepLabCut produces them, with gaps."""
    rng = np.random.default_rng(seed)
    d = np.empty((n, m, 3))
    d[..., 0] = rng.uniform(0, 2704, (n, m))
    d[..., 1] = rng.uniform(0, 1520, (n, m))
    d[..., 2] = rng.uniform(0, 1, (n, m))
    d[2 % n, 1 % m, :2] = np.nan  # a point DLC did not report
    d[5 % n, 3 % m, 2] = np.nan  # a likelihood that is NaN
    return d


def _columns(bodyparts, individuals=None, unique=()):
    """DeepLabCut's column tuples, in DeepLabCut's order."""
    if individuals is None:
        return [(SCORER, bp, c) for bp in bodyparts for c in ("x", "y", "likelihood")]
    cols = [(SCORER, ind, bp, c) for ind in individuals for bp in bodyparts for c in ("x", "y", "likelihood")]
    return cols + [(SCORER, "single", bp, c) for bp in unique for c in ("x", "y", "likelihood")]


def _frame(columns, values):
    pd = pytest.importorskip("pandas")
    names = ["scorer", "bodyparts", "coords"] if len(columns[0]) == 3 else \
        ["scorer", "individuals", "bodyparts", "coords"]
    return pd.DataFrame(values, columns=pd.MultiIndex.from_tuples(columns, names=names),
                        index=range(values.shape[0]))


class _Pickled(bytes):
    """An attribute PyTables stores pickled: a fixed-length ASCII string (text is UTF-8)."""


def _set_attrs(obj, attrs: dict) -> None:
    """PyTables' attribute types: text as fixed-length UTF-8 strings, pickles as ASCII ones,
    numbers as numpy scalars."""
    for k, v in attrs.items():
        if isinstance(v, _Pickled):
            obj.attrs.create(k, v, dtype=h5py.string_dtype("ascii", len(v)))
        elif isinstance(v, bytes):
            obj.attrs.create(k, v, dtype=h5py.string_dtype("utf-8", len(v)))
        else:
            obj.attrs[k] = v


def _h5py_fixed(path, columns, values, key="df_with_missing"):
    """pandas' fixed HDF5 layout for a float frame with a column MultiIndex, written with h5py."""
    with h5py.File(path, "w") as f:
        g = f.create_group(key)
        for k, v in {"CLASS": b"GROUP", "VERSION": b"1.0", "pandas_type": b"frame", "encoding": b"UTF-8",
                     "errors": b"strict", "ndim": np.int64(2), "nblocks": np.int64(1),
                     "axis0_variety": b"multi", "axis0_nlevels": np.int64(len(columns[0])),
                     "axis1_variety": b"regular", "block0_items_variety": b"multi",
                     "block0_items_nlevels": np.int64(len(columns[0]))}.items():
            _set_attrs(g, {k: v})
        names = ["scorer", "bodyparts", "coords"] if len(columns[0]) == 3 else \
            ["scorer", "individuals", "bodyparts", "coords"]
        for prefix in ("axis0", "block0_items"):
            for i, name in enumerate(names):
                levels = sorted({c[i] for c in columns})
                lv = g.create_dataset(f"{prefix}_level{i}", data=np.array([s.encode() for s in levels]))
                for k, v in {"CLASS": b"ARRAY", "FLAVOR": b"numpy", "VERSION": b"2.4", "kind": b"string",
                             "name": name.encode(), f"{prefix}_name{name}": name.encode(),
                             "transposed": np.uint8(1)}.items():
                    _set_attrs(lv, {k: v})
                codes = np.array([levels.index(c[i]) for c in columns], dtype=np.int8)
                lb = g.create_dataset(f"{prefix}_label{i}", data=codes)
                _set_attrs(lb, {"CLASS": b"ARRAY", "FLAVOR": b"numpy", "VERSION": b"2.4", "transposed": np.uint8(1)})
        ax1 = g.create_dataset("axis1", data=np.arange(values.shape[0], dtype=np.int64))
        for k, v in {"CLASS": b"ARRAY", "FLAVOR": b"numpy", "VERSION": b"2.4", "kind": b"integer",
                     "name": _Pickled(pickle.dumps(None, protocol=0)), "transposed": np.uint8(1)}.items():
            _set_attrs(ax1, {k: v})
        b = g.create_dataset("block0_values", data=np.asarray(values, dtype=np.float64))
        _set_attrs(b, {"CLASS": b"ARRAY", "FLAVOR": b"numpy", "VERSION": b"2.4", "transposed": np.uint8(1)})


def _h5py_table(path, columns, values, kind_attr: bytes | None = None):
    """The parts of pandas' ``format="table"`` layout that hold the data: the compound
    ``/df_with_missing/table`` and its ``values_block_0_kind`` attribute (PyTables pickles
    attributes with protocol 0, as ``pickle.dumps(labels, protocol=0)``)."""
    n, c = values.shape
    dtype = np.dtype([("index", "<i8"), ("values_block_0", "<f8", (c,))])
    rows = np.zeros(n, dtype=dtype)
    rows["index"] = np.arange(n)
    rows["values_block_0"] = values
    with h5py.File(path, "w") as f:
        g = f.create_group("df_with_missing")
        _set_attrs(g, {"pandas_type": b"frame_table", "table_type": b"appendable_frame"})
        t = g.create_dataset("table", data=rows)
        _set_attrs(t, {"CLASS": b"TABLE", "values_block_0_kind": _Pickled(
            kind_attr if kind_attr is not None else pickle.dumps(list(columns), protocol=0))})


def _expected(d: np.ndarray):
    xy = d[..., :2].copy()
    lik = np.nan_to_num(d[..., 2].copy(), nan=0.0)
    gone = ~np.isfinite(xy).all(-1)
    xy[gone] = np.nan
    lik[gone] = 0.0
    return xy, lik


def _check(kp: Keypoints, d: np.ndarray, bodyparts=BODYPARTS):
    xy, lik = _expected(d)
    assert kp.bodyparts == list(bodyparts)
    assert kp.scorer == SCORER
    np.testing.assert_array_equal(kp.xy, xy)
    np.testing.assert_array_equal(kp.likelihood, lik)


# ----------------------------------------------------------------------------------------- CSV


def test_single_animal_csv_as_written_by_dlc(tmp_path):
    d = _detections()
    path = tmp_path / "cam1DLC_resnet50.csv"
    _frame(_columns(BODYPARTS), d.reshape(len(d), -1)).to_csv(path)
    kp = read_keypoints(path)
    _check(kp, d)
    assert kp.source == str(path) and kp.frames == 12
    assert kp.likelihood[2, 1] == 0.0 and np.isnan(kp.xy[2, 1]).all() and kp.likelihood[5, 3] == 0.0


def test_single_animal_csv_literal_text(tmp_path):
    """The layout itself, as text (runs without pandas)."""
    text = (f"scorer,{SCORER},{SCORER},{SCORER},{SCORER},{SCORER},{SCORER}\n"
            "bodyparts,nose,nose,nose,tail1,tail1,tail1\n"
            "coords,x,y,likelihood,x,y,likelihood\n"
            "0,812.25,433.5,0.998,,,0.01\n"
            "1,815.0,431.75,,100.5,200.25,0.9\n")
    path = tmp_path / "cam.csv"
    path.write_text(text)
    kp = read_keypoints(path)
    assert kp.bodyparts == ["nose", "tail1"]
    np.testing.assert_array_equal(kp.xy[0, 0], [812.25, 433.5])
    assert np.isnan(kp.xy[0, 1]).all()
    np.testing.assert_array_equal(kp.likelihood, [[0.998, 0.0], [0.0, 0.9]])


def test_csv_numbers_read_to_the_last_bit(tmp_path):
    """Rows of plain numbers are read at once, the rest cell by cell: both give exactly what
    ``float`` gives each cell (17-digit values, exponents, 'nan', and Python's '1_5' that the
    fast reader leaves to the slow one)."""
    rng = np.random.default_rng(5)
    values = rng.normal(0, 1e3, size=(40, 6)) * 10.0 ** rng.integers(-8, 8, size=(40, 6))
    values[:, [2, 5]] = rng.random((40, 2))  # likelihoods
    rows = [",".join([str(i), *(repr(float(x)) for x in v)]) for i, v in enumerate(values)]
    rows[7] = "7,1e-300,2.5E+3,nan,-0.0,1.7976931348623157e308,0.5"
    rows[9] = "9,1_5,2,0.25,4,5,0.75"
    path = tmp_path / "cam.csv"
    path.write_text("scorer" + ",S" * 6 + "\nbodyparts,a,a,a,b,b,b\ncoords,x,y,likelihood,x,y,likelihood\n"
                    + "\n".join(rows) + "\n")
    kp = read_keypoints(path)
    expected = np.array([[float(c) for c in r.split(",")[1:]] for r in rows]).reshape(40, 2, 3)
    np.testing.assert_array_equal(kp.xy, expected[..., :2])
    np.testing.assert_array_equal(kp.likelihood, np.nan_to_num(expected[..., 2], nan=0.0))


def test_multi_animal_csv_literal_text(tmp_path):
    """The multi-animal layout as text (runs without pandas): 4 header rows, a 'single' block."""
    text = ("scorer,S,S,S,S,S,S,S,S,S\n"
            "individuals,ind1,ind1,ind1,ind2,ind2,ind2,single,single,single\n"
            "bodyparts,nose,nose,nose,nose,nose,nose,lure,lure,lure\n"
            "coords,x,y,likelihood,x,y,likelihood,x,y,likelihood\n"
            "0,1.0,2.0,0.5,3.0,4.0,0.75,5.0,6.0,1.0\n"
            "1,,,,7.0,8.0,0.25,9.0,10.0,0.125\n")
    path = tmp_path / "ma.csv"
    path.write_text(text)
    with pytest.warns(UserWarning, match="2 individuals"):
        one = read_keypoints(path)
    np.testing.assert_array_equal(one.likelihood, [[0.5], [0.0]])
    two = read_keypoints(path, individual="ind2")
    np.testing.assert_array_equal(two.xy[:, 0], [[3, 4], [7, 8]])
    lure = read_keypoints(path, individual="single")
    assert lure.bodyparts == ["lure"]
    np.testing.assert_array_equal(lure.likelihood, [[1.0], [0.125]])


def test_write_dlc_csv_is_byte_identical_to_pandas(tmp_path):
    d = _detections(30)
    xy, lik = _expected(d)
    kp = Keypoints(bodyparts=BODYPARTS, xy=xy, likelihood=lik, scorer=SCORER)
    ours = tmp_path / "ours.csv"
    write_dlc_csv(ours, kp)
    theirs = tmp_path / "pandas.csv"
    _frame(_columns(BODYPARTS), np.concatenate([xy, lik[..., None]], -1).reshape(30, -1)).to_csv(theirs)
    assert ours.read_bytes() == theirs.read_bytes()


def test_write_then_read_round_trip(tmp_path):
    d = _detections(7, 3)
    xy, lik = _expected(d)
    kp = Keypoints(bodyparts=["a", "b,c", 'say "d"'], xy=xy, likelihood=lik, scorer="me")
    write_dlc_csv(tmp_path / "k.csv", kp)
    back = read_keypoints(tmp_path / "k.csv")
    assert back.bodyparts == kp.bodyparts and back.scorer == "me"
    np.testing.assert_array_equal(back.xy, xy)
    np.testing.assert_array_equal(back.likelihood, lik)


def test_multi_animal_csv(tmp_path):
    n = 9
    d = np.concatenate([_detections(n, 4, seed=1), _detections(n, 4, seed=2), _detections(n, 1, seed=5)], axis=1)
    path = tmp_path / "ma.csv"
    _frame(_columns(BODYPARTS, ["cheetah1", "cheetah2"], unique=["lure"]), d.reshape(n, -1)).to_csv(path)
    with pytest.warns(UserWarning, match=r"ma\.csv: 2 individuals \(cheetah1, cheetah2\); using 'cheetah1'"):
        first = read_keypoints(path)
    _check(first, d[:, :4])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        second = read_keypoints(path, individual="cheetah2")
        single = read_keypoints(path, individual="single")
    _check(second, d[:, 4:8])
    _check(single, d[:, 8:], ["lure"])
    with pytest.raises(InputError,
                       match=r"^ma\.csv: no individual 'cheetah3' \(the file has cheetah1, cheetah2, single\)$"):
        read_keypoints(path, individual="cheetah3")


def test_multi_animal_with_one_individual_does_not_warn(tmp_path):
    d = _detections(5)
    path = tmp_path / "one.csv"
    _frame(_columns(BODYPARTS, ["ind1"]), d.reshape(5, -1)).to_csv(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _check(read_keypoints(path), d)


def test_labelled_data_csv_with_path_index(tmp_path):
    """``CollectedData_<scorer>.csv``: a 3-level row index and x, y only (human labels)."""
    pd = pytest.importorskip("pandas")
    cols = pd.MultiIndex.from_product([["Joe"], ["nose", "l_eye"], ["x", "y"]], names=["scorer", "bodyparts", "coords"])
    index = pd.MultiIndex.from_tuples([("labeled-data", "run1", f"img{i:03d}.png") for i in range(3)])
    values = np.array([[10.0, 20.0, 30.0, 40.0], [11.0, 21.0, np.nan, np.nan], [12.0, 22.0, 32.0, 42.0]])
    path = tmp_path / "CollectedData_Joe.csv"
    pd.DataFrame(values, columns=cols, index=index).to_csv(path)
    assert path.read_text().startswith("scorer,,,Joe")
    kp = read_keypoints(path)
    assert kp.bodyparts == ["nose", "l_eye"] and kp.scorer == "Joe"
    np.testing.assert_array_equal(kp.likelihood, [[1, 1], [1, 0], [1, 1]])
    np.testing.assert_array_equal(kp.xy[2], [[12, 22], [32, 42]])


# ------------------------------------------------------------------------------------------ H5


def test_h5_table_format_as_analyze_videos_writes_it(tmp_path):
    pytest.importorskip("tables")
    d = _detections()
    path = tmp_path / "cam1DLC_resnet50.h5"
    _frame(_columns(BODYPARTS), d.reshape(len(d), -1)).to_hdf(path, key="df_with_missing", format="table", mode="w")
    _check(read_keypoints(path), d)


def test_h5_table_multi_animal(tmp_path):
    pytest.importorskip("tables")
    n = 6
    d = np.concatenate([_detections(n, 4, seed=1), _detections(n, 4, seed=2)], axis=1)
    path = tmp_path / "ma_el.h5"
    _frame(_columns(BODYPARTS, ["a", "b"]), d.reshape(n, -1)).to_hdf(path, key="df_with_missing", format="table",
                                                                      mode="w")
    _check(read_keypoints(path, individual="b"), d[:, 4:])


def test_h5_fixed_format(tmp_path):
    pytest.importorskip("tables")
    d = _detections()
    path = tmp_path / "fixed.h5"
    _frame(_columns(BODYPARTS), d.reshape(len(d), -1)).to_hdf(path, key="df_with_missing", mode="w")
    _check(read_keypoints(path), d)


def test_h5py_written_layouts(tmp_path):
    """Both HDF5 layouts written with h5py alone; read here, and by pandas where installed."""
    d = _detections()
    values = d.reshape(len(d), -1)
    fixed, table = tmp_path / "fixed.h5", tmp_path / "table.h5"
    _h5py_fixed(fixed, _columns(BODYPARTS), values)
    _h5py_table(table, _columns(BODYPARTS), values)
    _check(read_keypoints(fixed), d)
    _check(read_keypoints(table), d)
    try:
        import pandas as pd
        import tables  # noqa: F401
    except ImportError:
        return
    # the h5py fixed layout is what pandas reads (and writes) ...
    pd.testing.assert_frame_equal(pd.read_hdf(fixed, "df_with_missing"), _frame(_columns(BODYPARTS), values),
                                  check_index_type=False)
    # ... and the table attribute is byte for byte what pandas + PyTables write
    real = tmp_path / "real.h5"
    _frame(_columns(BODYPARTS), values).to_hdf(real, key="df_with_missing", format="table", mode="w")
    with h5py.File(real) as a, h5py.File(table) as b:
        ta, tb = a["df_with_missing/table"], b["df_with_missing/table"]
        assert ta.attrs["values_block_0_kind"] == tb.attrs["values_block_0_kind"]
        assert ta.dtype == tb.dtype
        np.testing.assert_array_equal(ta["values_block_0"], tb["values_block_0"])


def test_malicious_pickle_in_h5_attribute_does_not_run(tmp_path):
    marker = tmp_path / "pwned"
    # a protocol-0 pickle that calls builtins.open(marker, "w"): creating the file proves execution
    payload = f"cbuiltins\nopen\n(V{marker}\nVw\ntR.".encode()
    live = tmp_path / "live"
    pickle.loads(f"cbuiltins\nopen\n(V{live}\nVw\ntR.".encode()).close()
    assert live.exists()  # the payload is real: unpickling it runs code

    d = _detections()
    path = tmp_path / "evil.h5"
    _h5py_table(path, _columns(BODYPARTS), d.reshape(len(d), -1), kind_attr=payload)
    with pytest.raises(InputError,
                       match=r"^evil\.h5: H5 attribute values_block_0_kind is a pickle that would run code"):
        read_keypoints(path)
    assert not marker.exists()


def test_malicious_pickle_in_pandas_written_file(tmp_path):
    pytest.importorskip("tables")
    marker = tmp_path / "pwned"
    d = _detections()
    path = tmp_path / "evil.h5"
    _frame(_columns(BODYPARTS), d.reshape(len(d), -1)).to_hdf(path, key="df_with_missing", format="table", mode="w")
    payload = np.bytes_(f"cos\nsystem\n(Vtouch {marker}\ntR.".encode())
    with h5py.File(path, "r+") as f:
        for attrs in (f["df_with_missing"].attrs, f["df_with_missing/table"].attrs):
            for k in list(attrs):
                if k in ("info", "non_index_axes", "values_cols", "index_cols", "data_columns", "values_block_0_kind"):
                    attrs[k] = payload
    with pytest.raises(InputError, match="would run code"):
        read_keypoints(path)
    assert not marker.exists()


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
def test_literal_unpickle_matches_pickle_for_literals(protocol):
    value = [("scorer", "ind1", "nose", "x"), ("s", "é", "b", "likelihood"), {"names": ["a", None, 3, 2.5, True]},
             (), [-7, 2 ** 70, 1e-300]]
    if protocol >= 3:  # earlier protocols pickle bytes through a codecs call
        value.append(b"raw")
    data = pickle.dumps(value, protocol=protocol)
    assert _literal_unpickle(data, Path("f.h5"), "attr") == pickle.loads(data)


def test_literal_unpickle_refuses_objects():
    import collections

    data = pickle.dumps([collections.OrderedDict(a=1)], protocol=2)
    with pytest.raises(InputError, match="would run code"):
        _literal_unpickle(data, Path("f.h5"), "attr")
    with pytest.raises(InputError, match="not a readable pickle"):
        _literal_unpickle(b"\x80\x05garbage", Path("f.h5"), "attr")


# -------------------------------------------------------------------------------- bad files


def _dlc_text(rows: list[str]) -> str:
    head = [f"scorer,{SCORER},{SCORER},{SCORER}", "bodyparts,nose,nose,nose", "coords,x,y,likelihood"]
    return "\n".join(head + rows) + "\n"


BAD_FILES = {
    "empty.csv": ("", "file is empty"),
    "blank.csv": ("\n\n  \n", "file is empty"),
    "nonsense.csv": ("hello,world\n1,2\n", "not a DeepLabCut CSV: the first row must start with 'scorer'"),
    "words.csv": ("The quick brown fox.", "not a DeepLabCut CSV"),
    "header_only.csv": (_dlc_text([]), "no data rows"),
    "not_dlc_header.csv": ("scorer,a,a\nfoo,b,b\ncoords,x,y\n0,1,2\n", "header rows must be scorer, bodyparts, coords"),
    "truncated.csv": (_dlc_text(["0,1.0,2.0,0.9", "1,1.5,2."]), "line 5 has 3 cells, the header has 4"),
    "ragged.csv": (_dlc_text(["0,1.0,2.0,0.9,7.0", "1,1.5,2.5,0.8"]), "line 4 has 5 cells"),
    "text_value.csv": (_dlc_text(["0,1.0,abc,0.9"]), "line 4, column 3: not a number: 'abc'"),
    "ragged_header.csv": (f"scorer,{SCORER},{SCORER},{SCORER}\nbodyparts,nose,nose\ncoords,x,y,likelihood\n0,1,2,3\n",
                          "ragged header"),
    "bad_coord.csv": ("scorer,S,S,S\nbodyparts,nose,nose,nose\ncoords,x,y,z\n0,1,2,3\n", "unknown coordinate 'z'"),
    "no_y.csv": ("scorer,S,S\nbodyparts,nose,nose\ncoords,x,likelihood\n0,1,0.5\n", "has no 'y' column"),
    "two_scorers.csv": ("scorer,A,A,B\nbodyparts,nose,nose,nose\ncoords,x,y,likelihood\n0,1,2,3\n", "several scorers"),
    "infinite.csv": (_dlc_text(["0,inf,2.0,0.9"]), "infinite"),
    "binary.csv": (b"\x00\xff\xfe\x01garbage\x9c", "binary"),
    "bad.h5": (b"\x89HDF\r\n\x1a\n" + b"\x00" * 40, "not a readable HDF5 file"),
}


@pytest.mark.parametrize("name", sorted(BAD_FILES))
def test_bad_keypoint_files_give_one_line_naming_the_file(tmp_path, name):
    content, expected = BAD_FILES[name]
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(InputError) as info:
        read_keypoints(path)
    message = str(info.value)
    assert message.startswith(f"{name}: ") and "\n" not in message
    assert expected in message


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(InputError, match=r"^gone\.csv: no such file$"):
        read_keypoints(tmp_path / "gone.csv")
    with pytest.raises(InputError, match="is a directory"):
        read_keypoints(tmp_path)


def test_h5_without_a_dataframe(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["data"] = np.zeros(3)
    with pytest.raises(InputError, match=r"^other\.h5: not a DeepLabCut H5 file: no pandas DataFrame"):
        read_keypoints(path)


# ---------------------------------------------------------------------------- bodyparts, frames


def test_match_bodyparts():
    kp = Keypoints(bodyparts=["Nose", "l_eye", "lure", "R-Eye", "tail_tip"], xy=np.zeros((2, 5, 2)),
                   likelihood=np.ones((2, 5)))
    match = match_bodyparts(kp, ["nose", "l_eye", "r_eye", "spine"])
    np.testing.assert_array_equal(match.index, [0, 1, 3, -1])
    assert match.unknown == ["lure", "tail_tip"]
    assert match.missing == ["spine"]
    index, unknown, missing = match  # unpacks like a tuple
    assert unknown == ["lure", "tail_tip"]


def test_exact_name_wins_over_loose_match():
    kp = Keypoints(bodyparts=["Nose", "nose"], xy=np.zeros((1, 2, 2)), likelihood=np.ones((1, 2)))
    assert match_bodyparts(kp, ["nose"]).index.tolist() == [1]
    assert match_bodyparts(kp, ["NOSE"]).index.tolist() == [0]


def test_select_markers_orders_and_fills():
    d = _detections(4, 3)
    xy, lik = _expected(d)
    kp = Keypoints(bodyparts=["a", "b", "c"], xy=xy, likelihood=lik, scorer="s", source="x.csv")
    sel = select_markers(kp, ["c", "zz", "a"])
    assert sel.bodyparts == ["c", "zz", "a"] and sel.source == "x.csv"
    np.testing.assert_array_equal(sel.xy[:, 0], xy[:, 2])
    np.testing.assert_array_equal(sel.xy[:, 2], xy[:, 0])
    assert np.isnan(sel.xy[:, 1]).all() and (sel.likelihood[:, 1] == 0).all()


def test_check_same_frames_names_the_odd_file():
    a = Keypoints(["n"], np.zeros((10, 1, 2)), np.ones((10, 1)), source="/data/cam1.csv")
    b = Keypoints(["n"], np.zeros((9, 1, 2)), np.ones((9, 1)), source="/data/cam2.csv")
    assert check_same_frames([a, a]) == 10
    with pytest.raises(InputError, match=r"^cam2\.csv: has 9 frames but cam1\.csv has 10"):
        check_same_frames([a, b])


def test_more_individuals_than_are_solved_at_once_is_one_line(tmp_path):
    """read_tracks of a multi-animal file with 65 individuals (64 at most, as the SLEAP and OpenPose readers)."""
    from graph.io.keypoints import read_tracks

    inds = [f"a{i}" for i in range(65)]
    rows = [["scorer"] + ["s"] * (3 * 65), ["individuals"] + [i for i in inds for _ in range(3)],
            ["bodyparts"] + ["nose"] * (3 * 65), ["coords"] + ["x", "y", "likelihood"] * 65, ["0"] + ["1.0"] * (3 * 65)]
    path = tmp_path / "many.csv"
    path.write_text("\n".join(",".join(r) for r in rows) + "\n")
    with pytest.raises(InputError, match=r"^many\.csv: 65 individuals; at most 64 are solved at once$"):
        read_tracks(path)
