"""A row written from its fields (CsvSink.write_row, the fused rows' path) and from its
dict (every other path) must give the same line."""

import io
import math

import numpy as np
import pytest

from visvec.data import AttitudeSolution, Status
from visvec.output import PoseRow, RateRow, attitude_row
from visvec.rotations import expmap
from visvec.sinks import CsvSink, row_writer


def _rows():
    R = expmap(np.array([0.3, -0.2, 1.1]))
    cov = np.array([[2e-6, 3e-7, 0.0], [3e-7, 1e-6, -1e-7], [0.0, -1e-7, 4e-6]])
    sol = AttitudeSolution(Status.OK, R_nb=R, cov_b=cov, rms_px=0.123456, n_points=4)
    yield attitude_row(3, 1.2345678, sol, Status.OK, ("fix_unconfirmed", "x", "x"), 0.25)
    yield attitude_row(4, 1.3, None, Status.NO_TARGET, ("no_fix_yet",), 0.1, 7)
    yield PoseRow(5, 2.0, Status.OK, math.nan, 3, 0.5, (), pose=np.array([1.5, -2.25, 91.0]),
                  sigma=np.array([0.1, 0.2, 0.3]), time_unix=1.7e9 + 0.1234567)  # fmt: skip
    yield RateRow(6, 2.5, Status.REJECTED, 0.7, 9, 1.0, ("too_few_stars",))


@pytest.mark.parametrize("row", list(_rows()), ids=lambda r: f"{type(r).__name__}-{r.status}")
def test_a_row_from_its_fields_is_the_row_from_its_dict(row):
    by_fields, by_dict = io.StringIO(), io.StringIO()
    row_writer(CsvSink(by_fields, row.columns))(row)
    CsvSink(by_dict, row.columns).write(row.as_dict())
    assert by_fields.getvalue() == by_dict.getvalue()
    assert list(row.as_dict()) == list(row.columns)
    line = by_fields.getvalue().splitlines()[1].split(",")
    assert len(line) == len(row.columns)
    if not row.ok:
        # a row that is not ok leaves its numbers empty
        assert line[3] == "" and line[row.columns.index("rms_px")] == ""


def test_a_row_of_other_columns_goes_by_its_dict():
    """A sink of other columns (an attitude sink given a pose row) refuses the extra
    fields as it always did, not writes them under the wrong names."""
    row = next(r for r in _rows() if isinstance(r, PoseRow))
    sink = CsvSink(io.StringIO(), next(_rows()).columns)
    with pytest.raises(ValueError, match="fields not in the columns"):
        sink.write_row(row)
