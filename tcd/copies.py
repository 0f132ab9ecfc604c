"""The kernels of state.get_rows / put_rows: several fields of one 1-D shape copied to or from
one packed f64 array in one launch (kernels live in a module without `from __future__ import
annotations`: Taichi reads their annotations as objects)."""
import taichi as ti


def _column_offsets(fields) -> tuple:
    """The first column of each field in the packed array, then the array's width."""
    offsets, col = [], 0
    for f in fields:
        offsets.append(col)
        col += f.n if isinstance(f, ti.MatrixField) else 1
    return tuple(offsets) + (col,)


@ti.kernel
def _rows_out(fields: ti.template(), out: ti.types.ndarray(dtype=ti.f64, ndim=2), n: ti.i32):
    offsets = ti.static(_column_offsets(fields))
    for r in range(n):
        for k in ti.static(range(len(fields))):
            if ti.static(isinstance(fields[k], ti.MatrixField)):
                for c in ti.static(range(fields[k].n)):
                    out[r, offsets[k] + c] = ti.cast(fields[k][r][c], ti.f64)
            else:
                out[r, offsets[k]] = ti.cast(fields[k][r], ti.f64)


@ti.kernel
def _rows_in(fields: ti.template(), arr: ti.types.ndarray(dtype=ti.f64, ndim=2), m: ti.i32,
             rows: ti.i32):
    offsets = ti.static(_column_offsets(fields))
    for r in range(rows):
        for k in ti.static(range(len(fields))):
            if ti.static(isinstance(fields[k], ti.MatrixField)):
                for c in ti.static(range(fields[k].n)):
                    if r < m:
                        fields[k][r][c] = ti.cast(arr[r, offsets[k] + c], fields[k].dtype)
                    else:
                        fields[k][r][c] = ti.cast(0, fields[k].dtype)
            else:
                if r < m:
                    fields[k][r] = ti.cast(arr[r, offsets[k]], fields[k].dtype)
                else:
                    fields[k][r] = ti.cast(0, fields[k].dtype)
