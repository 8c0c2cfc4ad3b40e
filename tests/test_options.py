"""Every solve option has a range: NaN, infinity and impossible values are one-line errors."""

import math

import pytest

from graph.types import SolveOptions


@pytest.mark.parametrize("field,value,words", [
    ("fps", 1e5, "fps must be between 0.01 and 10000"),
    ("fps", math.nan, "fps must be between"),
    ("fps", -3.0, "fps must be between"),
    ("fps", 1e-300, "fps must be between"),
    ("motion_scale", math.inf, "motion_scale must be positive"),
    ("motion_scale", -1.0, "motion_scale must be positive"),
    ("lag_seconds", -0.5, "lag_seconds must be positive"),
    ("lag_seconds", math.nan, "lag_seconds must be positive"),
    ("max_iterations", 10**12, "max_iterations must be from 1 to 10000"),
    ("measurement_std_px", math.nan, "measurement_std_px must be a positive number"),
    ("measurement_std_px", math.inf, "measurement_std_px must be a positive number"),
    ("time_offsets", [0.0, math.nan], "time_offsets must be finite"),
    ("body_lengths", {"spine": math.inf}, "body_lengths must be positive"),
])
def test_out_of_range_options_are_refused(field, value, words):
    with pytest.raises(ValueError) as e:
        SolveOptions(**{field: value})
    assert words in str(e.value) and "\n" not in str(e.value)


def test_the_defaults_are_valid_and_estimate_the_body():
    o = SolveOptions()
    assert o.body == "estimate" and o.sync == "given" and o.time_offsets is None
