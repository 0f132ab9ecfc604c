"""state.get_rows / put_rows: several fields copied in one kernel launch must give exactly what
Taichi's own per-field copies (state.get / state.put) give: the same values, dtypes and
zeroed tail, in either precision."""
import numpy as np
import pytest
import taichi as ti

from tcd import state
from tcd.backend import numpy_real, real as real_dtype


@pytest.fixture
def fields(backend):
    """A record like the solver's: AoS scalars and a vector, a plain vector field, an int."""
    real = real_dtype()
    f = state._struct(8, ti.field(ti.i32), state._real_row(), state._vec_row())
    return f + (state._vec(8), ti.field(real, shape=8), ti.field(ti.i32, shape=8))


def values(rng, m):
    real = numpy_real()
    x = rng.normal(size=(m, 3))
    x[1, 2] = np.nan                              # a bond's broken_position while intact
    return [rng.integers(-2**31, 2**31, m).astype(np.int32), rng.normal(size=m), x,
            rng.normal(size=(m, 3)).astype(real), np.full(m, 1e-300), np.arange(m) * 7]


def test_put_rows_writes_what_put_writes_and_zeroes_the_rest(fields):
    rng = np.random.default_rng(3)
    vals = values(rng, 5)
    for f in fields:                              # a tail left by an earlier user of the fields
        f.fill(9)
    state.put_rows(fields, vals)
    rows = [f.to_numpy() for f in fields]
    for f, v in zip(fields, vals):
        state.put(f, v)
    for f, got in zip(fields, rows):
        want = f.to_numpy()
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)  # NaN where NaN, bit for bit otherwise
        assert not np.any(want[5:])


def test_get_rows_reads_what_get_reads(fields):
    rng = np.random.default_rng(4)
    for f, v in zip(fields, values(rng, 8)):
        state.put(f, v)
    for n in (0, 1, 6, 8):
        got = state.get_rows(fields, n)
        for f, g in zip(fields, got):
            want = state.get(f, n)
            assert g.dtype == want.dtype and g.shape == want.shape
            np.testing.assert_array_equal(g, want)


def test_row_copies_refuse_what_does_not_fit(fields):
    with pytest.raises(ValueError, match="one 1-D shape"):
        state.get_rows(fields + (state._real(9),), 3)
    with pytest.raises(ValueError, match="one row count"):
        state.put_rows(fields[:2], [np.zeros(3, np.int32), np.zeros(4)])
    with pytest.raises(ValueError, match="9 rows do not fit fields of 8"):
        state.put_rows(fields[:1], [np.zeros(9, np.int32)])
