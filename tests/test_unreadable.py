"""A file the system will not open or read is one line naming it, the same from every reader
(:func:`graph.errors.unreadable`): no such file, a directory, or the system's reason."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from graph.calibrate.views import read_detections
from graph.errors import InputError, unreadable
from graph.io.calibration import load_calibration
from graph.io.keypoints import read_keypoints
from graph.io.results import read_anipose_csv
from graph.simulate import load_truth

READERS = [(read_keypoints, "a keypoint file"), (load_calibration, "a calibration file"),
           (read_anipose_csv, "an Anipose CSV"), (read_detections, "a detections file"), (load_truth, "a truth file")]
# a file every process may open whose reading fails in the kernel: page 0 of its own memory is not mapped
UNREADABLE = Path("/proc/self/mem")


def test_the_system_error_becomes_one_line_naming_the_file():
    assert str(unreadable(FileNotFoundError(errno.ENOENT, "No such file or directory"), "a/b.csv")) == \
        "b.csv: no such file"
    assert str(unreadable(IsADirectoryError(errno.EISDIR, "Is a directory"), "runs/", "a keypoint file")) == \
        "runs: is a directory, not a keypoint file"
    assert str(unreadable(PermissionError(errno.EACCES, "Permission denied"), "/x/cal.toml")) == \
        "cal.toml: cannot read: Permission denied"
    assert unreadable(OSError("disk on fire"), "f.h5").path == "f.h5"
    assert str(unreadable(OSError("disk on fire"), "f.h5")) == "f.h5: cannot read: disk on fire"


@pytest.mark.parametrize("read, what", READERS, ids=[r.__name__ for r, _ in READERS])
def test_every_reader_says_the_same(read, what, tmp_path):
    with pytest.raises(InputError, match=r"^gone\.x: no such file$"):
        read(tmp_path / "gone.x")
    folder = tmp_path / "a_folder"
    folder.mkdir()
    with pytest.raises(InputError, match=rf"^a_folder: is a directory, not {what}$"):
        read(folder)
    if UNREADABLE.exists():
        with pytest.raises(InputError, match=r"^mem: cannot read: Input/output error$"):
            read(UNREADABLE)


def test_an_empty_truth_file_is_named_not_a_traceback(tmp_path):
    empty = tmp_path / "truth.npz"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match=r"^truth\.npz: not a truth file written by 'acinoset simulate'"):
        load_truth(empty)
