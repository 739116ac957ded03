"""TUM trajectory files: one pose per line ``t tx ty tz qx qy qz qw`` (s, m, quaternion x, y, z, w).

Timestamps are written as seconds with 9 decimals from the integer nanoseconds (exact, no float rounding),
and read back exactly with :class:`decimal.Decimal`, so ``ts_ns`` survives a round trip bit for bit. Lines
starting with ``#`` and blank lines are comments. The reader also accepts commas as separators (some tools
write them).
This is the format ``evo`` reads for estimates (``evo_ape tum gt.txt est.txt``).
"""

from __future__ import annotations

import decimal
from pathlib import Path

import numpy as np

from runtime.geometry import R_to_quat_xyzw, quat_xyzw_to_R

__all__ = ["TumFormatError", "write_tum", "read_tum", "ns_to_seconds_str", "seconds_str_to_ns"]

_HEADER = "# timestamp[s] tx ty tz qx qy qz qw"


class TumFormatError(ValueError):
    """A TUM trajectory file is malformed; the message names the file and the line."""


def ns_to_seconds_str(t_ns: int) -> str:
    """Integer nanoseconds -> exact decimal seconds with 9 decimals.

    >>> ns_to_seconds_str(1403636579763555584)
    '1403636579.763555584'
    >>> ns_to_seconds_str(-5)
    '-0.000000005'
    """
    t = int(t_ns)
    sign = "-" if t < 0 else ""
    s, ns = divmod(abs(t), 1_000_000_000)
    return f"{sign}{s}.{ns:09d}"


def seconds_str_to_ns(text: str) -> int:
    """Decimal seconds (any notation, e.g. ``1403636579.763555584`` or ``1.4e9``) -> nanoseconds, rounded.

    >>> seconds_str_to_ns("1403636579.763555584")
    1403636579763555584
    """
    d = decimal.Decimal(text.strip()) * 1_000_000_000
    if not d.is_finite():
        raise ValueError(f"timestamp {text!r} is not finite")
    return int(d.to_integral_value(rounding=decimal.ROUND_HALF_EVEN))


def write_tum(path: str | Path, ts_ns: np.ndarray, T_w_b: np.ndarray, header: bool = True) -> Path:
    """Write poses as a TUM trajectory.

    Args:
        path: output file (parent folders are created).
        ts_ns: (N,) integer timestamps [ns].
        T_w_b: (N, 4, 4) poses (body in world); rotations must be orthonormal (|R R^T - I| < 1e-6).
        header: write a ``#`` header line.

    Returns:
        The path written.

    Raises:
        ValueError: shapes differ, timestamps are not integers, or a pose is not finite / not rigid.
    """
    path = Path(path)
    ts = np.asarray(ts_ns)
    T = np.asarray(T_w_b, dtype=np.float64)
    if ts.ndim != 1 or ts.dtype.kind not in "iu":
        raise ValueError(f"ts_ns must be a 1-D integer array [ns], got shape {ts.shape} dtype {ts.dtype}")
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] != ts.shape[0]:
        raise ValueError(f"T_w_b must have shape ({ts.shape[0]}, 4, 4) to match ts_ns, got {T.shape}")
    if not np.isfinite(T).all():
        i = int(np.flatnonzero(~np.isfinite(T).reshape(len(T), -1).all(1))[0])
        raise ValueError(f"pose {i} (t={int(ts[i])} ns) is not finite")
    R = T[:, :3, :3]
    err = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2)) if len(T) else np.zeros(0)
    if (err > 1e-6).any():
        i = int(np.argmax(err))
        raise ValueError(
            f"pose {i} (t={int(ts[i])} ns) has a non-orthonormal rotation (|R R^T - I| = {err[i]:.2e})"
        )
    q = R_to_quat_xyzw(R) if len(T) else np.zeros((0, 4))
    p = T[:, :3, 3]
    lines = [_HEADER] if header else []
    for t, pi, qi in zip(ts.tolist(), p, q, strict=True):
        lines.append(
            f"{ns_to_seconds_str(t)} {pi[0]:.9f} {pi[1]:.9f} {pi[2]:.9f} "
            f"{qi[0]:.9f} {qi[1]:.9f} {qi[2]:.9f} {qi[3]:.9f}"
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory.

    Args:
        path: the file; ``#`` lines and blank lines are skipped; fields separated by spaces/tabs or commas.

    Returns:
        ts_ns (N,) int64 [ns] (strictly increasing), T (N, 4, 4) float64 poses (quaternions normalised).

    Raises:
        TumFormatError: missing file, wrong column count, unparsable value, NaN, zero quaternion or
        non-increasing timestamps, naming the file and line.
    """
    path = Path(path)
    if not path.is_file():
        raise TumFormatError(f"{path}: missing file")
    ts: list[int] = []
    vals: list[list[float]] = []
    numbers: list[int] = []
    for ln, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise TumFormatError(
                f"{path}: line {ln}: expected 8 columns 't tx ty tz qx qy qz qw', got {len(parts)}"
            )
        try:
            t = seconds_str_to_ns(parts[0])
        except (decimal.InvalidOperation, ValueError):
            raise TumFormatError(
                f"{path}: line {ln}: timestamp {parts[0]!r} is not a number of seconds"
            ) from None
        try:
            v = [float(x) for x in parts[1:]]
        except ValueError:
            raise TumFormatError(f"{path}: line {ln}: non-numeric value in {s!r}") from None
        if not np.isfinite(v).all():
            raise TumFormatError(f"{path}: line {ln}: NaN/inf value in {s!r}")
        ts.append(t)
        vals.append(v)
        numbers.append(ln)
    ts_arr = np.asarray(ts, dtype=np.int64)
    v_arr = np.asarray(vals, dtype=np.float64).reshape(-1, 7)
    bad = np.flatnonzero(np.diff(ts_arr) <= 0)
    if bad.size:
        j = int(bad[0])
        raise TumFormatError(f"{path}: line {numbers[j + 1]}: timestamps not strictly increasing")
    norm = np.linalg.norm(v_arr[:, 3:], axis=1)
    bad = np.flatnonzero(norm < 1e-6)
    if bad.size:
        raise TumFormatError(f"{path}: line {numbers[int(bad[0])]}: zero quaternion")
    T = np.zeros((len(ts_arr), 4, 4))
    T[:, :3, :3] = quat_xyzw_to_R(v_arr[:, 3:])
    T[:, :3, 3] = v_arr[:, :3]
    T[:, 3, 3] = 1.0
    return ts_arr, T
