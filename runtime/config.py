"""Settings from mappings: nested dataclasses built from a dict (e.g. a Hydra config group), checked by key.

Every numeric setting has a range (:func:`value_range`): the per-class table :data:`RANGES` first, then rules by
the name (sigmas, tolerances and scales are positive, ratios lie in [0, 1], everything else is non-negative);
values must be finite. A value outside its range raises ValueError naming the key and the range.
"""

from __future__ import annotations

import dataclasses
import math

_INF = math.inf

#: ``{class name: {field: (low, high)}}``, inclusive bounds; these win over the name rules of :func:`value_range`.
RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "FeatureConfig": {
        "max_features": (1, _INF),
        "grid_cols": (1, 1000),
        "grid_rows": (1, 1000),
        "fast_threshold": (0, 255),
    },
    "TrackerConfig": {"win_size": (3, 255), "pyr_levels": (0, 10), "max_iter": (1, _INF)},
    "TriangulationConfig": {"min_views": (2, _INF)},
    "BackendConfig": {"window_size": (2, _INF), "lm_max_iterations": (1, _INF)},
    "CoastConfig": {"lm_max_iterations": (1, _INF)},
    "RelocConfig": {"max_attempts": (0, _INF), "max_hamming": (0, 256), "guided_max_hamming": (0, 256)},
    "SlamConfig": {"max_track_views": (2, _INF)},
    "DenseConfig": {"n_code_keyframes": (1, _INF), "relin_tol": (0, _INF)},
    "DynamicInitConfig": {"accel_bias_weight": (0, _INF)},
    "DepthFactorConfig": {"chunk_size": (1, _INF)},
    "DenseMapConfig": {"stride": (1, _INF)},
}
_POSITIVE = ("sigma", "_tol", "eps", "scale", "gravity", "factor", "huber_k", "voxel", "delta")
_UNIT = ("ratio", "confidence", "quality_level")
_TINY = 5e-324  # the smallest positive float: "> 0" as an inclusive bound


def value_range(cls, name: str) -> tuple[float, float]:
    """Inclusive ``(low, high)`` of numeric field ``name`` of dataclass ``cls``.

    >>> from runtime.slam import SlamConfig
    >>> value_range(type(SlamConfig().backend), "window_size")
    (2, inf)
    >>> value_range(type(SlamConfig().backend), "pixel_sigma")[0] > 0
    True
    """
    for klass in type.mro(cls):
        table = RANGES.get(klass.__name__, {})
        if name in table:
            return table[name]
    if any(p in name for p in _POSITIVE):
        return (_TINY, _INF)
    if name.endswith(_UNIT):
        return (0.0, 1.0)
    return (0, _INF)


def _check_range(cls, name: str, v, key: str) -> None:
    lo, hi = value_range(cls, name)
    if not math.isfinite(v):
        raise ValueError(f"setting {key} must be finite, got {v!r}")
    if not lo <= v <= hi:
        low = "> 0" if lo == _TINY else f">= {lo:g}"
        high = "" if hi == _INF else f" and <= {hi:g}"
        raise ValueError(f"setting {key}={v!r} is out of range: must be {low}{high}")


def dataclass_from_dict(cls, d, path: str):
    """Build dataclass ``cls`` from mapping ``d``; nested dataclass fields take nested mappings.

    Unknown keys, values of the wrong kind and numbers outside their range (:func:`value_range`) raise
    ValueError naming the key (``path.key``); numbers are cast to the default's type (an integer field refuses
    2.5).

    >>> from dataclasses import dataclass
    >>> @dataclass
    ... class A:
    ...     n: int = 1
    >>> dataclass_from_dict(A, {"n": 3.0}, "a")
    A(n=3)
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for k, v in dict(d).items():
        if k not in fields:
            raise ValueError(f"unknown setting {path}.{k} (known: {', '.join(fields)})")
        default = getattr(cls(), k)
        if dataclasses.is_dataclass(default):
            if not isinstance(v, dict):
                raise ValueError(f"setting {path}.{k} must be a mapping, got {v!r}")
            kwargs[k] = dataclass_from_dict(type(default), v, f"{path}.{k}")
        else:
            kwargs[k] = _checked(default, v, f"{path}.{k}")
            if isinstance(kwargs[k], (int, float)) and not isinstance(kwargs[k], bool):
                _check_range(cls, k, kwargs[k], f"{path}.{k}")
    return cls(**kwargs)


def _checked(default, v, key: str):
    """``v`` for a field whose default is ``default``: bools stay bools, numbers become the default's type."""
    if isinstance(default, bool):
        if not isinstance(v, bool):
            raise ValueError(f"setting {key} must be true/false, got {v!r}")
    elif isinstance(default, (int, float)):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"setting {key} must be a number, got {v!r}")
        if isinstance(default, int) and not float(v).is_integer():
            raise ValueError(f"setting {key} must be an integer, got {v!r}")
        v = type(default)(v)
    elif isinstance(default, str) and not isinstance(v, str):
        raise ValueError(f"setting {key} must be a string, got {v!r}")
    return v


def preset_yaml(obj, header: str = "") -> str:
    """The YAML text of a settings dataclass instance: every key with its value and the comment of its field in
    the source (the one source of the generated presets, :mod:`runtime.presets`).

    >>> from runtime.init import InitConfig
    >>> preset_yaml(InitConfig()).splitlines()[0].split("#")[0].strip()
    'still_duration_s: 1.0'
    """
    lines = [f"# {h}".rstrip() for h in header.splitlines()]
    _emit(obj, 0, lines)
    return "\n".join(lines) + "\n"


def _emit(obj, indent: int, lines: list) -> None:
    import inspect
    import re

    comments = {}
    for cls in reversed(type(obj).__mro__):
        try:
            src = inspect.getsource(cls)
        except (OSError, TypeError):
            continue
        for m in re.finditer(r"^\s+(\w+): [^=\n]+=[^#\n]*#\s*(.+)$", src, re.M):
            comments[m.group(1)] = m.group(2).strip()
    pad = "  " * indent
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            doc = (inspect.getdoc(type(v)) or "").splitlines()
            lines.append(f"{pad}{f.name}:" + (f"  # {doc[0]}" if doc else ""))
            _emit(v, indent + 1, lines)
            continue
        text = f"{pad}{f.name}: {_yaml_value(v)}"
        c = comments.get(f.name)
        lines.append(f"{text:<46}# {c}" if c else text)


def _yaml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if v is None:
        return "null"
    if isinstance(v, float):
        r = repr(v)
        return r.replace("e", ".0e", 1) if "e" in r and "." not in r else r  # YAML 1.1 floats need the dot
    return str(v)
