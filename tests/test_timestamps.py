import numpy as np
import pytest

from radarslam.errors import DataError
from radarslam.timestamps import check_timestamps_us


def test_integer_microseconds_pass_and_come_back_as_int64():
    out = check_timestamps_us([1.0, 2.0, 2.0], 3, "x", strictly_increasing=False)
    assert out.dtype == np.int64 and out.tolist() == [1, 2, 2]


@pytest.mark.parametrize(
    ("values", "strict", "match"),
    [
        ([1, 2, 2], True, r"f: timestamp 2 \(2 us\) repeats the previous one; .* strictly"),
        ([2, 1], False, r"f: timestamp 1 \(1 us\) is earlier than the previous one; .* sorted"),
        ([1.5, 2.0], False, r"f: timestamp 0 is 1.5; .* \(seconds given\? multiply by 1e6\)"),
        ([1, 2**62], True, r"f: timestamp 1 .* is out of range"),
        ([True, False], True, r"f: timestamps_us must be integer microseconds, got bool"),
        ([1, 2], True, r"f: \(2,\) timestamps for 3 poses"),
    ],
)
def test_bad_timestamps_name_the_first_offending_value(values, strict, match):
    n = 3 if match.endswith("3 poses") else len(values)
    with pytest.raises(DataError, match=match):
        check_timestamps_us(values, n, "f", strictly_increasing=strict)
