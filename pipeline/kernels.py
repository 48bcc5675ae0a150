"""Compiled loops for the hottest array passes of the pipeline (numba, when installed: the optional `fast` extra),
each computing exactly the numpy/scipy expression it replaces, operation for operation, so results are
bit-identical either way:

- :func:`filtfilt_columns`: ``scipy.signal.sosfiltfilt(sos, x, axis=0, padlen=padlen)`` with odd padding, column by
  column in one buffer (scipy copies the columns into rows, pads, filters, reverses and copies back, one array pass
  each; the filter's own recursion is a small part of the time);
- :func:`central_slopes`, :func:`hermite_eval`: the slopes, interval search and cubic Hermite evaluation of
  :func:`pipeline.prepare._interp_columns` in one pass each instead of a dozen array passes;
- :func:`shifted_context`: the shifted, masked context rows of :func:`pipeline.prepare._context_scores` (the
  correlation sums stay numpy's own);
- :func:`saturated_runs`: the clipped-gyro run tests of :func:`pipeline.prepare.saturation_mask`;
- :func:`si_block`: the unit conversion and the finiteness and order checks of :func:`pipeline.prepare.to_si` in
  one pass;
- :func:`row_norm`, :func:`cross_rows`: :func:`pipeline.signal_utils.row_norm` and ``cross_rows`` row by row
  (numpy makes a temporary array per product and sum).

Floating-point contraction (fused multiply-add) and reassociation stay off (numba's default without ``fastmath``),
which is what keeps each value the same as numpy's. ``cache=True``: a worker loads the compiled code from the
package's ``__pycache__`` instead of compiling again (compiling takes a few seconds, once per installation). The
signatures are given, so the compiled code is loaded when this module is imported (once per worker process) rather
than at the first call inside a session. Without numba (or with ``NUMBA_DISABLE_JIT=1``) every name is None and
the callers use the numpy paths.

Cost: importing numba and loading these loops adds about 140 MB to a process's resident set (about 90 MB of it
LLVM's shared library, shared between processes) and 0.2-0.25 s CPU at import.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

try:
    import numba
except ImportError:  # numba is optional (extra `fast`): the numpy paths give the same values
    numba = None
if numba is not None and numba.config.DISABLE_JIT:
    numba = None  # NUMBA_DISABLE_JIT=1 would run these loops as Python, far slower than the numpy paths

filtfilt_columns: Callable[..., None] | None = None
hermite_eval: Callable[..., None] | None = None
central_slopes: Callable[..., None] | None = None
saturated_runs: Callable[..., None] | None = None
si_block: Callable[..., bool] | None = None
shifted_context: Callable[..., None] | None = None
row_norm: Callable[..., None] | None = None
cross_rows: Callable[..., None] | None = None

if numba is not None:

    @numba.njit("void(f8[:, ::1], f8[:, ::1], f8[:, ::1], i8, i8, i8)", cache=True, nogil=True, inline="always")
    def _one_section_lanes(sos: np.ndarray, zi: np.ndarray, e: np.ndarray, ca: int, cb: int, cc: int) -> None:
        """Both passes of :func:`_filtfilt_columns` for a single section (a 2nd-order Butterworth, what every
        walking filter is) on the padded columns ``ca``, ``cb``, ``cc`` of ``e`` in place (equal indices repeat a
        column: its values are computed twice, the same). The three recursions run side by side with their states
        in local variables: kept in registers, each step waits for the multiply-adds only, not for the state's
        store and reload through memory, and the three independent chains overlap."""
        m = e.shape[0]
        b0, b1, b2, a1, a2 = sos[0, 0], sos[0, 1], sos[0, 2], sos[0, 4], sos[0, 5]
        for rev in range(2):
            first = 0 if rev == 0 else m - 1
            za0, za1 = zi[0, 0] * e[first, ca], zi[0, 1] * e[first, ca]
            zb0, zb1 = zi[0, 0] * e[first, cb], zi[0, 1] * e[first, cb]
            zc0, zc1 = zi[0, 0] * e[first, cc], zi[0, 1] * e[first, cc]
            for jj in range(m):
                j = jj if rev == 0 else m - 1 - jj
                xa, xb, xc = e[j, ca], e[j, cb], e[j, cc]
                ya = b0 * xa + za0
                yb = b0 * xb + zb0
                yc = b0 * xc + zc0
                za0 = b1 * xa - a1 * ya + za1
                zb0 = b1 * xb - a1 * yb + zb1
                zc0 = b1 * xc - a1 * yc + zc1
                za1 = b2 * xa - a2 * ya
                zb1 = b2 * xb - a2 * yb
                zc1 = b2 * xc - a2 * yc
                e[j, cc] = yc
                e[j, cb] = yb
                e[j, ca] = ya

    @numba.njit("void(f8[:, ::1], f8[:, ::1], f8[:, :], i8, f8[:, ::1])", cache=True, nogil=True)
    def _filtfilt_columns(sos: np.ndarray, zi: np.ndarray, x: np.ndarray, padlen: int, out: np.ndarray) -> None:
        """``out[:, c]`` = sosfiltfilt of ``x[:, c]`` (scipy's odd extension by ``padlen``, initial state ``zi`` times
        the first sample of each pass, direct-form II transposed sections as in scipy's ``_sosfilt``). The columns
        are filtered side by side, sample by sample: each column's recursion is a chain of dependent
        multiply-adds, and independent chains interleaved keep the processor busy. A single section goes to
        :func:`_one_section_lanes`, the same arithmetic with its states in registers."""
        n, k = x.shape
        n_sec = sos.shape[0]
        m = n + 2 * padlen
        e = np.empty((m, k))
        for j in range(padlen):
            for c in range(k):
                e[j, c] = 2.0 * x[0, c] - x[padlen - j, c]
                e[n + padlen + j, c] = 2.0 * x[n - 1, c] - x[n - 2 - j, c]
        e[padlen:padlen + n] = x
        if n_sec == 1:
            for c0 in range(0, k, 3):
                _one_section_lanes(sos, zi, e, c0, min(c0 + 1, k - 1), min(c0 + 2, k - 1))
            out[:] = e[padlen:padlen + n]
            return
        z = np.empty((n_sec, 2, k))
        for rev in range(2):
            # forward pass with state zi * ext[0]; then backward over its output, state zi * its last sample
            first = 0 if rev == 0 else m - 1
            for s in range(n_sec):
                for c in range(k):
                    z[s, 0, c] = zi[s, 0] * e[first, c]
                    z[s, 1, c] = zi[s, 1] * e[first, c]
            for jj in range(m):
                j = jj if rev == 0 else m - 1 - jj
                for c in range(k):
                    x_cur = e[j, c]
                    for s in range(n_sec):
                        x_new = sos[s, 0] * x_cur + z[s, 0, c]
                        z[s, 0, c] = sos[s, 1] * x_cur - sos[s, 4] * x_new + z[s, 1, c]
                        z[s, 1, c] = sos[s, 2] * x_cur - sos[s, 5] * x_new
                        x_cur = x_new
                    e[j, c] = x_cur
        out[:] = e[padlen:padlen + n]

    @numba.njit("void(f8[::1], f8[:, ::1], f8[:, ::1])", cache=True, nogil=True)
    def _central_slopes(t: np.ndarray, x: np.ndarray, m: np.ndarray) -> None:
        """``m[a] = (x[a + 1] - x[a - 1]) / (t[a + 1] - t[a - 1])`` for the inner samples ``0 < a < n - 1``."""
        for a in range(1, t.shape[0] - 1):
            h = t[a + 1] - t[a - 1]
            for c in range(x.shape[1]):
                m[a, c] = (x[a + 1, c] - x[a - 1, c]) / h

    @numba.njit("void(f8[::1], f8[::1], f8[:, ::1], f8[:, ::1], f8[::1], i8[::1], f8[:, ::1])", cache=True,
                nogil=True)
    def _hermite_eval(t_new: np.ndarray, t: np.ndarray, x: np.ndarray, m: np.ndarray, dt: np.ndarray,
                      i_all: np.ndarray, out: np.ndarray) -> None:
        """``i_all[r]`` = ``clip(searchsorted(t, t_new[r], "right") - 1, 0, n - 2)`` (by merging, restarted
        wherever ``t_new`` steps back; ``t_new`` finite) and ``out[r]`` = h00 x[i] + h10 h m[i] + h01 x[i+1] +
        h11 h m[i+1], the basis and the sums in :func:`pipeline.prepare._interp_columns`'s order: h00 =
        (2u^3 - 3u^2) + 1, h10 h = ((u^3 - 2u^2) + u) h, h01 = -2u^3 + 3u^2, h11 h = (u^3 - u^2) h, u^3 = (u u) u."""
        n = t.shape[0]
        k = x.shape[1]
        j = 0
        for r in range(t_new.shape[0]):
            tn = t_new[r]
            if r > 0 and tn < t_new[r - 1]:
                j = 0
            while j < n and t[j] <= tn:
                j += 1
            i = min(max(j - 1, 0), n - 2)
            i_all[r] = i
            h = dt[i]
            u = (tn - t[i]) / h
            u2 = u * u
            u3 = u * u * u
            w0 = 2.0 * u3 - 3.0 * u2 + 1.0
            w1 = (u3 - 2.0 * u2 + u) * h
            w2 = -2.0 * u3 + 3.0 * u2
            w3 = (u3 - u2) * h
            for c in range(k):
                acc = w0 * x[i, c]
                acc += m[i, c] * w1
                acc += x[i + 1, c] * w2
                acc += m[i + 1, c] * w3
                out[r, c] = acc

    @numba.njit("void(f8[:, :], f8[::1])", cache=True, nogil=True)
    def _row_norm(x: np.ndarray, out: np.ndarray) -> None:
        """``out[i] = sqrt((x0 x0 + x1 x1) + x2 x2)`` of each row."""
        for i in range(x.shape[0]):
            x0, x1, x2 = x[i, 0], x[i, 1], x[i, 2]
            out[i] = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)

    @numba.njit("void(f8[:, :], f8[:, :], f8[:, ::1])", cache=True, nogil=True)
    def _cross_rows(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
        """``out[i] = a[i] x b[i]`` (``b`` of one row: the same vector for every ``i``), ``a1 b2 - a2 b1``, ..."""
        one = b.shape[0] == 1
        for i in range(a.shape[0]):
            k = 0 if one else i
            a0, a1, a2 = a[i, 0], a[i, 1], a[i, 2]
            b0, b1, b2 = b[k, 0], b[k, 1], b[k, 2]
            out[i, 0] = a1 * b2 - a2 * b1
            out[i, 1] = a2 * b0 - a0 * b2
            out[i, 2] = a0 * b1 - a1 * b0

    @numba.njit("void(f8[:, :], b1[::1], i8[::1], i8[::1], i8, f8[::1], f8[:, :, ::1], b1[:, ::1])", cache=True,
                nogil=True)
    def _shifted_context(g: np.ndarray, bad: np.ndarray, c: np.ndarray, lags: np.ndarray, sign: int,
                         mean: np.ndarray, b: np.ndarray, ok: np.ndarray) -> None:
        """``src = c + sign * lag``: ``ok[l, j]`` = src inside the signal and not masked, ``b[l, j]`` =
        ``(g[clip(src)] - mean) * ok`` (the rows :func:`pipeline.prepare._context_scores` correlates)."""
        n = g.shape[0]
        for li in range(lags.shape[0]):
            for j in range(c.shape[0]):
                src = c[j] + sign * lags[li]
                inside = src >= 0 and src < n
                okv = inside and not bad[src]
                ok[li, j] = okv
                row = min(max(src, 0), n - 1)
                w = 1.0 if okv else 0.0
                for d in range(g.shape[1]):
                    b[li, j, d] = (g[row, d] - mean[d]) * w

    @numba.njit("b1(f8[::1], f8[:, :], f8[:, :], f8, f8, f8[:, ::1])", cache=True, nogil=True)
    def _si_block(t: np.ndarray, gyr: np.ndarray, acc: np.ndarray, gyr_scale: float, acc_scale: float,
                  out: np.ndarray) -> bool:
        """``out = [gyr * gyr_scale | acc * acc_scale]`` (a scale of 1.0: a copy, which ``x * 1.0`` is), and whether
        every time stamp and value is finite and the stamps strictly increase: the usual case, nothing to drop
        or sort (:func:`pipeline.prepare.to_si`)."""
        n = t.shape[0]
        clean = True
        for i in range(n):
            ti = t[i]
            if not np.isfinite(ti) or (i > 0 and not ti - t[i - 1] > 0.0):
                clean = False
            for c in range(3):
                g = gyr[i, c] * gyr_scale
                a = acc[i, c] * acc_scale
                out[i, c] = g
                out[i, 3 + c] = a
                if not (np.isfinite(g) and np.isfinite(a)):
                    clean = False
        return clean

    @numba.njit("void(f8[:, :], f8[::1], i8, b1[::1])", cache=True, nogil=True)
    def _saturated_runs(gyr: np.ndarray, thr: np.ndarray, run_len: int, out: np.ndarray) -> None:
        """``out[i] |= `` some axis with a threshold (``thr`` not NaN) has ``run_len`` samples with
        ``|g| >= thr`` in the window ``[j - run_len // 2, j + (run_len - 1) // 2]`` of some ``j`` whose own window
        holds ``i``: the two ``np.convolve(..., np.ones(run_len), mode="same")`` tests of
        :func:`pipeline.prepare.saturation_mask`, as window counts (integers: exact)."""
        n = gyr.shape[0]
        lo, hi = run_len // 2, (run_len - 1) // 2
        at = np.empty(n, dtype=np.int64)
        run = np.zeros(n + 1, dtype=np.int64)  # prefix counts of the samples that end a full run
        for axis in range(gyr.shape[1]):
            t = thr[axis]
            if np.isnan(t):
                continue
            for i in range(n):
                at[i] = 1 if abs(gyr[i, axis]) >= t else 0
            cnt = 0
            for i in range(min(hi, n)):
                cnt += at[i]
            for j in range(n):
                if j + hi < n:
                    cnt += at[j + hi]
                if j - lo - 1 >= 0:
                    cnt -= at[j - lo - 1]
                run[j + 1] = run[j] + (1 if cnt >= run_len else 0)
            for i in range(n):
                a, b = max(i - lo, 0), min(i + hi, n - 1)
                if run[b + 1] - run[a] > 0:
                    out[i] = True

    central_slopes = _central_slopes
    saturated_runs = _saturated_runs
    si_block = _si_block
    shifted_context = _shifted_context
    row_norm = _row_norm
    cross_rows = _cross_rows
    filtfilt_columns = _filtfilt_columns
    hermite_eval = _hermite_eval
